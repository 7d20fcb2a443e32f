"""Validation on the held-out split: error per level of detail (a table like the paper's Table 2).

The table is plain JSON-ready data: it is written next to the model as NAME.json and stored in the
ONNX metadata under `contract.META_VALIDATION`.
"""

from __future__ import annotations

import numpy as np
import torch

from neumip.core import contract as C

from neumip.training.model.material import NeuMIPMaterial


@torch.no_grad()
def predict(
    material: NeuMIPMaterial,
    queries: np.ndarray,
    pyramid: list[torch.Tensor] | None = None,
    offset_texture: torch.Tensor | None = None,
    batch: int = 1 << 16,
) -> np.ndarray:
    """(N, 7) float32 queries -> (N, 3) float32 RGB, evaluated in batches on the material's device."""
    device = next(material.parameters()).device
    out = np.empty((queries.shape[0], C.RGB_DIM), np.float32)
    for lo in range(0, queries.shape[0], batch):
        q = torch.from_numpy(np.array(queries[lo : lo + batch], np.float32)).to(device)  # a writable copy
        out[lo : lo + batch] = material(q, pyramid, offset_texture).cpu().numpy()
    return out


def errors(pred: np.ndarray, target: np.ndarray) -> dict[str, float]:
    """Error figures of (n, 3) predictions against (n, 3) targets."""
    diff = pred.astype(np.float64) - target
    log_diff = np.log1p(np.maximum(pred, -0.1)) - np.log1p(np.maximum(target, -0.1))
    return {
        "n": int(target.shape[0]),
        "mse": float(np.mean(diff * diff)),
        "rel_l1": float(np.abs(diff).sum() / max(np.abs(target).sum(), 1e-30)),
        "log_mse": float(np.mean(log_diff.astype(np.float64) ** 2)),
        "target_mean": float(np.mean(target)),
        "answer_mean": float(np.mean(pred)),
    }


def validation_table(
    pred: np.ndarray, target: np.ndarray, sigma: np.ndarray, resolution: int
) -> dict:
    """Per-level errors. pred, target (N, 3); sigma (N,) -> {"levels": [...], "overall": {...}}.

    A query counts towards the level nearest its continuous level of detail
    (`contract.level_of_detail`). mse is in linear RGB (the paper's measure), rel_l1 is
    sum|pred - target| / sum|target|, log_mse is the MSE of log1p values (what comb2 optimises);
    target_mean / answer_mean is how much darker than its data a level answers on the whole.
    """
    level = np.rint(C.level_of_detail(np.asarray(sigma, np.float64), resolution)).astype(int)
    rows = []
    for lvl in range(int(np.log2(resolution)) + 1):
        mask = level == lvl
        if mask.any():
            rows.append({"level": lvl, **errors(pred[mask], target[mask])})
    return {"resolution": resolution, "levels": rows, "overall": errors(pred, target)}


def format_table(table: dict) -> str:
    """The validation table as aligned text lines (for logs, the CLI and the README)."""
    lines = [f"{'level':>5} {'texels':>7} {'n':>8} {'query MSE x1e-3':>16} {'rel L1':>8} {'log MSE':>9} "
             f"{'data / answer':>13}"]
    res = table["resolution"]
    for row in table["levels"] + [{"level": "all", **table["overall"]}]:
        texels = f"{res >> row['level']}^2" if isinstance(row["level"], int) else ""
        lines.append(
            f"{row['level']:>5} {texels:>7} {row['n']:>8} {row['mse'] * 1e3:>16.4f} "
            f"{row['rel_l1']:>8.4f} {row['log_mse']:>9.5f} {_ratio(row):>13}"
        )
    return "\n".join(lines)


def _ratio(row: dict) -> str:
    """A row's mean target over its mean answer ('' for a table written before answers' means were kept)."""
    answer = row.get("answer_mean")
    return "" if answer is None else f"{row['target_mean'] / answer:.3f}" if answer > 0 else "inf"
