"""An evaluator that keeps every query buffer the renderer sends it."""

from __future__ import annotations

import numpy as np

from neumip.engines.local import LocalMaterials


class Recording(LocalMaterials):
    """LocalMaterials that keeps every query buffer it evaluates (in call order)."""

    def __init__(self, folder):
        super().__init__(folder)
        self.calls: list[np.ndarray] = []

    def evaluate(self, material, queries):
        self.calls.append(np.array(queries))
        return super().evaluate(material, queries)
