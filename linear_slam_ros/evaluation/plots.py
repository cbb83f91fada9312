"""Pictures of joined maps (matplotlib, imported lazily; Agg backend, no display needed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap


def plot_map(local_map: LocalMap, path: Path, title: str = "") -> None:
    """Draw the robot path (x-y) and the features of a map, in its own frame, to a PNG file."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = local_map.dim
    poses = [(local_map.frame_id, np.zeros(d))]
    for i in np.flatnonzero(local_map.kinds == POSE).tolist():
        poses.append((int(local_map.ids[i]), local_map.x[local_map.offsets[i] : local_map.offsets[i] + d]))
    poses.sort(key=lambda item: item[0])
    xy = np.array([p for _, p in poses])
    feature_indices = np.flatnonzero(local_map.kinds == FEATURE).tolist()
    feats = np.array([local_map.x[local_map.offsets[i] : local_map.offsets[i] + d] for i in feature_indices])
    fig, ax = plt.subplots(figsize=(7, 7))
    ax.plot(xy[:, 0], xy[:, 1], "-", color="tab:blue", lw=0.8, label=f"robot path ({len(poses)} poses)")
    if feats.size:
        ax.plot(feats[:, 0], feats[:, 1], "+", color="tab:red", ms=4, label=f"features ({len(feats)})")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or f"joined map in the frame of pose {local_map.frame_id}")
    ax.legend(loc="best")
    ax.grid(True, lw=0.3)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
