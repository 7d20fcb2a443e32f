"""Write a Triton / KServe model repository from a folder of exported materials.

    repo/
      README.md                 which neumip made it, how, and how to serve it
      NAME/config.pbtxt         Triton's ModelConfig (`neumip.server.model_config`)
      NAME/1/model.onnx         the material's ONNX file, unchanged (metadata included)
      NAME/1/model.py           --backend python only (`neumip.server.triton_python_model`)

Every material is loaded first (contract version, graph) and nothing is written if one fails. The
repository is built in a temporary folder beside the target and renamed into place, so an
interrupted export never leaves a half-written repository under the target's name.

Each config states dims [-1] in and out (queries (N, 7) or query groups (N, 5 + 2 K) -> (N, 3 K),
`neumip.core.contract`). A model file of an older contract version is refused, with the command that
upgrades it (`neumip export OLD.onnx -o NEW.onnx`).
"""

from __future__ import annotations

import importlib.metadata
import logging
import os
import shutil
import tempfile
from pathlib import Path

from neumip.core import contract as C
from neumip.core.errors import NeumipError
from neumip.engines.local import Material, load_folder

from neumip.server.model_config import TritonOptions, model_config, to_pbtxt
from neumip.server.registry import MODEL_VERSION

log = logging.getLogger(__name__)

PYTHON_MODEL = Path(__file__).with_name("triton_python_model.py")
"""The python backend's ``model.py`` (copied into each version folder)."""


class RepositoryError(NeumipError, ValueError):
    """The repository cannot be written (no materials, a material that fails, target in the way)."""


def neumip_version() -> str:
    try:
        return importlib.metadata.version("neumip")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover - running from a bare tree
        return "unknown"


def readme(materials: dict[str, Material], options: TritonOptions, command: str) -> str:
    """The repository's README.md: provenance, layout and how to serve it."""
    rows = "\n".join(
        f"| `{name}` | {m.metadata.get(C.META_CONTRACT, '?')} | {m.metadata.get(C.META_DESCRIPTION, '')} |"
        for name, m in sorted(materials.items())
    )
    python = "" if options.backend == "onnxruntime" else " Each version folder also holds `model.py`."
    return f"""# neumip model repository

Made by neumip {neumip_version()} with `{command}`.

Triton model repository, backend `{options.backend}`: one model per material, `NAME/config.pbtxt`
and `NAME/{MODEL_VERSION}/model.onnx`.{python} Every model takes `{C.ONNX_INPUT}` FP32 [N, {C.QUERY_DIM}]
(u, v, sigma, wi_x, wi_y, wo_x, wo_y) and answers `{C.ONNX_OUTPUT}` FP32 [N, {C.RGB_DIM}], or query groups
[N, 5 + 2 K] (wi_x, wi_y of each further light after the 7) answered [N, 3 K] (config dims [-1]); each ONNX file
carries its own metadata (`neumip.contract_version`, `neumip.config`, `neumip.validation`).
Batching: at most {options.max_batch_size} rows per request, dynamic batching towards
{options.preferred_batch_size} rows, waiting at most {options.max_queue_delay_us} us;
{options.instances} CPU instance(s) with {options.intra_op_threads} ONNX Runtime intra-op thread(s)
(0 = one per core).

| material | contract version | description |
|---|---|---|
{rows}

Serve it: `tritonserver --model-repository=$PWD`, or a KServe InferenceService with the Triton
runtime whose `storageUri` points at this folder (neumip's `docker/k8s/kserve-inferenceservice.yaml`).
"""


def write_model(folder: Path, material: Material, options: TritonOptions) -> None:
    """One material's model folder: config.pbtxt, 1/model.onnx (and 1/model.py for the python backend)."""
    version = folder / MODEL_VERSION
    version.mkdir(parents=True)
    (folder / "config.pbtxt").write_text(to_pbtxt(model_config(material.name, options)))
    shutil.copyfile(material.path, version / "model.onnx")
    if options.backend == "python":
        shutil.copyfile(PYTHON_MODEL, version / "model.py")


def export_repository(models: Path, out: Path, options: TritonOptions, force: bool = False,
                      command: str = "neumip export-repository") -> list[str]:
    """Write the repository of every material in `models` to `out`; returns the material names.

    Raises RepositoryError if no material is there, if one fails to load, or if `out` exists and is
    not empty (unless `force`, which replaces it once the new one is complete).
    """
    models, out = Path(models), Path(out)
    if not models.is_dir():
        raise RepositoryError(f"model folder {models} does not exist")
    materials, failed = load_folder(models)
    if failed:
        reasons = "; ".join(f"{name}: {why}" for name, why in sorted(failed.items()))
        raise RepositoryError(f"{len(failed)} material(s) in {models} cannot be exported ({reasons})")
    if not materials:
        raise RepositoryError(f"no *.onnx material in {models}")
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not force:
        raise RepositoryError(f"{out} exists and is not empty: choose another folder or pass --force")
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        for material in materials.values():
            write_model(staging / material.name, material, options)
        (staging / "README.md").write_text(readme(materials, options, command))
        staging.chmod(0o755)
        if out.exists():
            old = out.with_name(f".{out.name}.old-{os.getpid()}")
            out.rename(old)
            staging.rename(out)
            shutil.rmtree(old) if old.is_dir() else old.unlink()
        else:
            staging.rename(out)
    finally:
        if staging.exists():
            shutil.rmtree(staging)
    log.info("wrote a %s repository of %d material(s) to %s", options.backend, len(materials), out)
    return sorted(materials)
