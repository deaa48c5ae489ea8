"""What neighbours can add: the share of occupied ground-truth voxels the ego's LiDAR hits, alone and together
with its collaborators' LiDARs (ROS-free).

A voxel of the ego's grid is *hit* when a LiDAR return falls in it; a
collaborator's hits are its occupied voxels' centres carried into the ego's
frame (so within half a voxel). A collaboration gain can only come from what
the neighbours see and the ego does not (and from what a model infers around
it): these shares bound what fusion has to work with.
"""

from __future__ import annotations

import numpy as np

from co3sop_nodes.common.classes import CLASS_NAMES, NUM_CLASSES
from co3sop_nodes.inference.inputs import merged_occupancy
from co3sop_nodes.train.dataset import OccupancyDataset


def observed(dataset: OccupancyDataset) -> dict:
    grid = dataset.cfg.grid
    total, ego_hit, any_hit = (np.zeros(NUM_CLASSES, np.int64) for _ in range(3))
    for i in range(len(dataset)):
        s = dataset.sample(i)
        ego = s.ego.inputs["occupancy"][0].astype(bool)  # (X, Y, Z)
        union = (
            merged_occupancy(
                s.ego.inputs["occupancy"], [a.inputs["occupancy"] for a in s.others], s.neighbour_from_ego, grid
            )[0]
            > 0
        )
        labels = s.ego.labels
        occupied = (labels > 0) & (labels < NUM_CLASSES)
        total += np.bincount(labels[occupied], minlength=NUM_CLASSES)
        ego_hit += np.bincount(labels[occupied & ego], minlength=NUM_CLASSES)
        any_hit += np.bincount(labels[occupied & union], minlength=NUM_CLASSES)
    classes = {
        CLASS_NAMES[c]: {
            "voxels": int(total[c]),
            "ego": ego_hit[c] / total[c],
            "ego+collaborators": any_hit[c] / total[c],
        }
        for c in range(1, NUM_CLASSES)
        if total[c]
    }
    return {
        "samples": len(dataset),
        "all": {
            "voxels": int(total.sum()),
            "ego": ego_hit.sum() / total.sum(),
            "ego+collaborators": any_hit.sum() / total.sum(),
        },
        "classes": classes,
    }


def observed_table(result: dict, title: str) -> str:
    rows = [
        f"#### {title}: share of occupied ground-truth voxels hit by LiDAR ({result['samples']} samples)",
        "",
        "| class | voxels | ego (%) | ego + collaborators (%) | added by collaborators (points) |",
        "|---|---:|---:|---:|---:|",
    ]
    for name, r in [("all occupied", result["all"]), *result["classes"].items()]:
        rows.append(
            f"| {name} | {r['voxels']} | {100 * r['ego']:.2f} | {100 * r['ego+collaborators']:.2f} | "
            f"{100 * (r['ego+collaborators'] - r['ego']):.2f} |"
        )
    return "\n".join(rows)
