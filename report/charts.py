"""Figures of the report (matplotlib, small PNGs): image strips with FLIP maps, error against time,
the model trade-off, and the stability sweeps."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from neumip.report import metrics as Q
from neumip.report.methods import METHODS

COLORS = {"R": "black", "N": "tab:red", "N0": "tab:orange", "Nmaps": "tab:purple", "Nmaps0": "tab:pink",
          "C": "tab:blue", "Cmip": "tab:cyan"}
DPI = 80


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI)
    _plt().close(fig)
    return path


def strip(view_result: dict, path: Path, title: str) -> Path:
    """R and every compared method present (N, N0, Nmaps, Nmaps0, C, Cmip) tone-mapped (top) and their FLIP
    maps against R (bottom)."""
    plt = _plt()
    images, maps = view_result["images"], view_result["flip_maps"]
    exposure = view_result["reference"]["exposure"]
    names = [m for m in METHODS if m in images]
    h, w = images["R"].shape[:2]
    fig, axes = plt.subplots(2, len(names), figsize=(1.9 * len(names), 1.9 * 2 * h / w + 0.5), squeeze=False)
    for i, m in enumerate(names):
        axes[0, i].imshow(Q.tonemap(images[m], exposure), interpolation="nearest")
        axes[0, i].set_title(m, fontsize=9)
        if m in maps:
            axes[1, i].imshow(maps[m], cmap="magma", vmin=0, vmax=1, interpolation="nearest")
            axes[1, i].set_title(f"FLIP {np.mean(maps[m]):.3f}", fontsize=8)
        for ax in axes[:, i]:
            ax.set_xticks([])
            ax.set_yticks([])
    axes[1, 0].set_title("FLIP map vs R", fontsize=8)
    axes[1, 0].axis("off")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


def error_time(material_result: dict, views: list[str], path: Path, title: str) -> Path:
    """MSE against render seconds, log-log, one panel per distance view, one line per method."""
    plt = _plt()
    fig, axes = plt.subplots(1, len(views), figsize=(3.0 * len(views), 3.0), squeeze=False)
    for ax, view in zip(axes[0], views):
        res = material_result[view]
        for m, entries in res["methods"].items():
            spps = sorted(s for s in entries if "seconds" in entries[s] and "mse" in entries[s])
            t = [entries[s]["seconds"] for s in spps]
            e = [entries[s]["mse"] * 1e3 for s in spps]
            ax.loglog(t, e, "o-", color=COLORS.get(m), label=m, ms=3, lw=1)
        ax.axhline(res["reference"]["noise_mse"] * 1e3, color="grey", ls=":", lw=1, label="R noise")
        ax.set_title(view, fontsize=9)
        ax.set_xlabel("seconds", fontsize=8)
        ax.xaxis.set_minor_formatter(plt.NullFormatter())
        ax.grid(True, which="both", alpha=0.3)
        ax.tick_params(labelsize=7)
    axes[0, 0].set_ylabel("image MSE x1e-3", fontsize=8)
    axes[0, -1].legend(fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


def _tradeoff_color(point: dict) -> str:
    if point.get("maps"):
        return COLORS["Nmaps"] if point["offset"] else COLORS["Nmaps0"]
    return COLORS["N"] if point["offset"] else COLORS["N0"]


def tradeoff(points: dict, path: Path) -> Path:
    """What each configuration buys (validation and image error) against what it costs at render (queries
    per second) and at training (seconds), one labelled point each; map-informed ones in purple."""
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
    panels = ((axes[0], "validation_mse", "queries_per_second", "query MSE x1e-3 (held out)", "M queries / s (in-process)"),
              (axes[1], "image_mse", "queries_per_second", "image MSE x1e-3", "M queries / s (in-process)"),
              (axes[2], "image_mse", "training_seconds", "image MSE x1e-3", "training seconds (one thread)"))
    for ax, key, cost, xlabel, ylabel in panels:
        scale = 1e-6 if cost == "queries_per_second" else 1.0
        for name, p in points.items():
            if p.get(key) is None or p.get(cost) is None:
                continue
            xy = (p[key] * 1e3, p[cost] * scale)
            ax.scatter(*xy, s=14, color=_tradeoff_color(p))
            ax.annotate(name, xy, fontsize=7)
        ax.set_xlabel(xlabel, fontsize=8)
        ax.set_ylabel(ylabel, fontsize=8)
        ax.grid(True, alpha=0.3)
        ax.tick_params(labelsize=7)
    fig.tight_layout()
    return _save(fig, path)


def sweeps(results: dict, path: Path) -> Path:
    """Grazing, sigma and sub-texel sweeps of every material."""
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.2))
    for name, r in results.items():
        g, s, t = r["grazing"], r["sigma"], r["subtexel"]
        axes[0].plot(g["angle_deg"], g["mean"], label=name, lw=1)
        axes[1].semilogx(s["sigma"], s["mean"], label=name, lw=1)
        u = np.array(t["u"])
        axes[2].plot((u - u[0]) / (u[-1] - u[0]), t["luminance"], label=name, lw=1)
    axes[0].set_xlabel("view zenith (degrees)", fontsize=8)
    axes[1].set_xlabel("sigma (tiles)", fontsize=8)
    axes[2].set_xlabel("position across one finest texel", fontsize=8)
    for ax in axes:
        ax.set_ylabel("mean luminance", fontsize=8)
        ax.grid(True, alpha=0.3)
        ax.tick_params(labelsize=7)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    return _save(fig, path)


def horizon(images: dict, exposure: float, rows: dict, path: Path) -> Path:
    """The plane-to-the-horizon renders and their row-mean profiles."""
    plt = _plt()
    fig, axes = plt.subplots(1, len(images) + 1, figsize=(2.6 * (len(images) + 1), 2.6))
    for ax, (name, img) in zip(axes, images.items()):
        ax.imshow(Q.tonemap(img, exposure), interpolation="nearest")
        ax.set_title(name, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    for name, r in rows.items():
        axes[-1].plot(r["row_mean"], label=name, lw=1)
    axes[-1].set_xlabel("image row (top: horizon)", fontsize=8)
    axes[-1].set_ylabel("row mean luminance", fontsize=8)
    axes[-1].legend(fontsize=7)
    axes[-1].tick_params(labelsize=7)
    fig.tight_layout()
    return _save(fig, path)
