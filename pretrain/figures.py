"""Pictures of pretraining: BEV samples (inputs, true and predicted maps), training curves, the FOV mask, and the
prediction errors of the intention models (probe and pretraining)."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np

from pretrain.geometry import BEVGrid, bev_to_image
from pretrain.model import TARGETS
from sim.viz import save_figure


def pyplot():
    """matplotlib's pyplot on the Agg backend (files only)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _extent(grid: BEVGrid) -> list[float]:
    # top-down picture: horizontal axis = lateral y (left on the left), vertical = forward x (up)
    return [grid.y_bound[1], grid.y_bound[0], grid.x_bound[0], grid.x_bound[1]]


def plot_sample(path: Path, grid: BEVGrid, camera_names: list[str], rgb: np.ndarray, depth: np.ndarray,
                labels: np.ndarray, probs: np.ndarray, valid: np.ndarray, fov: np.ndarray, title: str) -> None:
    """One validation frame: camera images and depth (top), then true and predicted occupancy per target.

    Args:
        rgb: ``N x 3 x H x W`` uint8; depth: ``N x h x w`` m at the lift pixels.
        labels, probs: ``K x X x Y`` true occupancy and predicted probability; valid: ``K`` bool.
        fov: ``X x Y`` field-of-view mask (outlined).
    """
    plt = pyplot()
    n = len(camera_names)
    k = len(TARGETS)
    cols = max(2 * n, k)
    fig, axes = plt.subplots(3, cols, figsize=(2.6 * cols, 8.2), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for i, name in enumerate(camera_names):
        axes[0, i].imshow(rgb[i].transpose(1, 2, 0))
        axes[0, i].set_title(f"{name} RGB", fontsize=9)
        im = axes[0, n + i].imshow(np.where(depth[i] > 0, depth[i], np.nan), cmap="magma_r", vmin=0, vmax=8)
        axes[0, n + i].set_title(f"{name} depth (lift pixels, m)", fontsize=9)
    fig.colorbar(im, ax=axes[0, 2 * n - 1], fraction=0.046)
    ext = _extent(grid)
    fov_img = bev_to_image(fov.astype(float))
    for j, t in enumerate(TARGETS):
        for row, arr, what in ((1, labels[j].astype(float), "true"), (2, probs[j], "predicted")):
            ax = axes[row, j]
            ax.axis("on")
            ax.imshow(bev_to_image(arr), cmap="viridis", vmin=0, vmax=1, extent=ext, interpolation="nearest")
            ax.contour(np.linspace(ext[0], ext[1], fov_img.shape[1]), np.linspace(ext[3], ext[2], fov_img.shape[0]),
                       fov_img, levels=[0.5], colors="w", linewidths=0.6)
            ax.plot(0, 0, marker="^", color="r", markersize=7)
            ax.set_title(f"{what}: {t}" + ("" if valid[j] else " (beyond episode)"), fontsize=9)
            ax.tick_params(labelsize=7)
            if j == 0:
                ax.set_ylabel("forward x (m)", fontsize=8)
            if row == 2:
                ax.set_xlabel("lateral y (m), left ←", fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    save_figure(fig, path, 90)
    plt.close(fig)


def plot_curves(path: Path, log_csv: Path, history: list[dict[str, Any]]) -> None:
    """Training loss per step and validation IoU per target per epoch."""
    plt = pyplot()
    rows = []
    if Path(log_csv).is_file():
        with open(log_csv, newline="") as f:
            rows = list(csv.DictReader(f))
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    if rows:
        steps = [int(r["step"]) for r in rows]
        a.plot(steps, [float(r["loss"]) for r in rows], color="k", lw=1.2, label="mean")
        for t in TARGETS:
            a.plot(steps, [float(r[f"loss_{t}"]) for r in rows], lw=0.8, label=t)
    a.set_xlabel("step")
    a.set_ylabel("BCE (train, field of view)")
    a.set_yscale("log")
    a.legend(fontsize=8)
    a.grid(alpha=0.3)
    if history:
        steps = [h["step"] for h in history]
        for t in TARGETS:
            b.plot(steps, [h[f"iou_{t}"] for h in history], marker="o", label=t)
    b.axhline(0.5, color="gray", ls="--", lw=0.8)
    b.axhline(0.6, color="gray", ls=":", lw=0.8)
    b.set_ylim(0, 1)
    b.set_xlabel("step")
    b.set_ylabel("validation IoU (field of view)")
    b.legend(fontsize=8)
    b.grid(alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path, 100)
    plt.close(fig)


def plot_fov(path: Path, grid: BEVGrid, fov: np.ndarray) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(4.5, 3.4))
    ax.imshow(bev_to_image(fov.astype(float)), cmap="gray", extent=_extent(grid), vmin=0, vmax=1)
    ax.plot(0, 0, marker="^", color="r")
    ax.set_title(f"cameras' field of view in the BEV grid ({100 * fov.mean():.0f} % of cells)", fontsize=9)
    ax.set_xlabel("lateral y (m)")
    ax.set_ylabel("forward x (m)")
    fig.tight_layout()
    save_figure(fig, path, 100)
    plt.close(fig)


def plot_model_errors(path: Path, results: dict[str, dict[str, dict[str, Any]]], key: str, ylabel: str,
                      title: str) -> None:
    """Grouped bars: one bar per model (``results`` keys, in order) per sample group (the first model's groups
    with samples), height ``results[model][group][key]``, the group's ``n`` under its name."""
    plt = pyplot()
    first = next(iter(results.values()))
    groups = [g for g in first if first[g]["n"]]
    fig, ax = plt.subplots(figsize=(10, 3.8))
    w = 0.8 / len(results)
    for i, (m, r) in enumerate(results.items()):
        ax.bar(np.arange(len(groups)) + i * w, [r[g][key] for g in groups], w, label=m)
    ax.set_xticks(np.arange(len(groups)) + 0.4 - w / 2, [f"{g}\n(n={first[g]['n']})" for g in groups], fontsize=7)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)
