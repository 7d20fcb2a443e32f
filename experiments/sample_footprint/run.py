"""The report with each neural sample reading a smaller share of its pixel's footprint.

A render's samples each read ``contract.sample_footprint(n) = max(1/8, 1/sqrt(n))`` of the pixel's footprint
(pbrt-v4's rule): at 64 spp a view of 64 map texels a pixel reads the model at 8 texels (level 3), where turtle's
answers are dark and flat (experiments/level_share). Reading ``SCALE`` times that share (finer levels, where the
model is accurate) lets the pixel's own samples average the rest: less bias, more noise. This runs `neumip report`
with the rule scaled for the neural methods (their cache keys changed accordingly; R, C and Cmip are reused):

    python experiments/sample_footprint/run.py SCALE report --materials turtle --models DIR -o OUT --cache CACHE ...
"""

from __future__ import annotations

import math
import sys

from neumip.client.mitsuba import integrator
from neumip.core import contract
from neumip.report import renderer


def main() -> int:
    scale = float(sys.argv[1])

    def scaled(spp: int) -> float:
        return scale * max(contract.MIN_SAMPLE_FOOTPRINT, 1 / math.sqrt(max(spp, 1)))

    contract.sample_footprint = integrator.sample_footprint = scaled
    renderer.NEURAL_VERSION = f"{renderer.NEURAL_VERSION}+footprint{scale:g}"
    from neumip.client.cli import main as cli
    return cli(sys.argv[2:])


if __name__ == "__main__":
    sys.exit(main())
