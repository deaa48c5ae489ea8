"""Semantic occupancy metrics: per-class IoU and mIoU in the three conventions peers use (ROS-free).

Counts accumulate over a dataset (equivalent to Co3SOP's per-sample averaging
of tp / gt / pred). Voxels labelled 255 in the ground truth are ignored.

- "co3sop-readme": mean IoU over all 24 classes including empty; the Co3SOP
  README's numbers follow it (17 of 18 rows).
- "co3sop-code": mean over classes 1..23 (empty excluded), Co3SOP's code.
  Both Co3SOP conventions count a class absent from ground truth and
  prediction as IoU 0, as Co3SOP's code does.
- "surroundocc": geometry IoU (occupied vs empty) and mean over the semantic
  classes 1..23 that occur in the ground truth (absent classes are left out).

Intervals (`Bootstrap`): 95 % percentile intervals from resampling scenarios
with replacement, the counts pooled over each resample as for the point
estimate. Scenarios, not frames, are the unit: frames of one scenario (and
its CAVs, each the ego in turn) see the same town and are far from
independent. Paired differences resample the same scenarios for both sides.
"""

from __future__ import annotations

import numpy as np

from co3sop_nodes.common.classes import CLASS_NAMES, EMPTY, IGNORE, NUM_CLASSES

CONVENTIONS = ("co3sop-readme", "co3sop-code", "surroundocc")
SCORES = (*CONVENTIONS, "geometry")  # the three mIoUs and SurroundOcc's geometry IoU


def scores(tp: np.ndarray, gt: np.ndarray, pred: np.ndarray, geo: np.ndarray) -> dict[str, np.ndarray]:
    """Counts (..., K) and geometry counts (..., 3) -> each of SCORES (...) and per-class IoU (..., K, NaN: absent)."""
    union = gt + pred - tp
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.where(union > 0, tp / np.maximum(union, 1), np.nan)
    zero_absent = np.nan_to_num(iou, nan=0.0)
    present = np.where(gt[..., 1:] > 0, iou[..., 1:], np.nan)  # IoU is defined wherever the class is in the truth
    n_present = (gt[..., 1:] > 0).sum(-1)
    return {
        "co3sop-readme": zero_absent.mean(-1),
        "co3sop-code": zero_absent[..., 1:].mean(-1),
        "surroundocc": np.where(n_present > 0, np.nansum(present, -1) / np.maximum(n_present, 1), np.nan),
        "geometry": geo[..., 0] / np.maximum(geo[..., 1] + geo[..., 2] - geo[..., 0], 1),
        "iou": iou,
    }


class Confusion:
    """Per-class true positives, ground-truth and predicted voxel counts, and the same for geometry."""

    def __init__(self, classes: int = NUM_CLASSES):
        self.classes = classes
        self.tp = np.zeros(classes, np.int64)
        self.gt = np.zeros(classes, np.int64)
        self.pred = np.zeros(classes, np.int64)
        self.geo = np.zeros(3, np.int64)  # tp, gt, pred of occupied vs empty
        self.frames = 0

    def add(self, prediction: np.ndarray, truth: np.ndarray) -> None:
        """prediction, truth: label grids of one frame (same shape)."""
        valid = truth != IGNORE
        p, t = prediction[valid].astype(np.int64), truth[valid].astype(np.int64)
        self.tp += np.bincount(t[p == t], minlength=self.classes)[: self.classes]
        self.gt += np.bincount(t, minlength=self.classes)[: self.classes]
        self.pred += np.bincount(p, minlength=self.classes)[: self.classes]
        po, to = p != EMPTY, t != EMPTY
        self.geo += [int((po & to).sum()), int(to.sum()), int(po.sum())]
        self.frames += 1

    def merge(self, other: Confusion) -> Confusion:
        """In place: adds another confusion's counts (e.g. pooling scenarios)."""
        self.tp += other.tp
        self.gt += other.gt
        self.pred += other.pred
        self.geo += other.geo
        self.frames += other.frames
        return self

    def counts(self) -> dict:
        """The counts as JSON-ready lists (from_counts inverts it)."""
        return {
            "tp": self.tp.tolist(),
            "gt": self.gt.tolist(),
            "pred": self.pred.tolist(),
            "geo": self.geo.tolist(),
            "frames": self.frames,
        }

    @classmethod
    def from_counts(cls, counts: dict) -> Confusion:
        c = cls(len(counts["tp"]))
        for name in ("tp", "gt", "pred", "geo"):
            getattr(c, name)[:] = counts[name]
        c.frames = counts["frames"]
        return c

    def iou(self) -> np.ndarray:
        """(K,) IoU per class; NaN where the class is in neither ground truth nor prediction."""
        return scores(self.tp, self.gt, self.pred, self.geo)["iou"]

    def summary(self) -> dict:
        s = scores(self.tp, self.gt, self.pred, self.geo)
        return {
            "frames": self.frames,
            "per_class_iou": {
                CLASS_NAMES[c]: (None if np.isnan(s["iou"][c]) else float(s["iou"][c])) for c in range(self.classes)
            },
            "co3sop-readme": {"miou": float(s["co3sop-readme"])},
            "co3sop-code": {"miou": float(s["co3sop-code"])},
            "surroundocc": {"iou": float(s["geometry"]), "miou": float(s["surroundocc"])},
        }


def pooled(confusions: dict) -> Confusion:
    """One confusion of every scenario's counts."""
    total = Confusion(next(iter(confusions.values())).classes)
    for c in confusions.values():
        total.merge(c)
    return total


def point(summary: dict, score: str) -> float:
    """One of SCORES read from a Confusion.summary()."""
    return summary["surroundocc"]["iou"] if score == "geometry" else summary[score]["miou"]


class Bootstrap:
    """95 % intervals over scenarios (module docstring); one set of resamples shared by every run it scores."""

    def __init__(self, scenarios: list, draws: int = 2000, seed: int = 0):
        self.scenarios = list(scenarios)
        n = len(self.scenarios)
        self.counts = np.random.default_rng(seed).multinomial(n, np.full(n, 1 / n), size=draws)  # (B, S) times drawn

    def _resampled(self, confusions: dict) -> dict[str, np.ndarray]:
        missing = [k for k in self.scenarios if k not in confusions]
        if missing:
            raise ValueError(f"no counts for scenario(s) {missing}")
        stack = [
            np.stack([getattr(confusions[k], a) for k in self.scenarios]) for a in ("tp", "gt", "pred", "geo")
        ]  # (S, K) / (S, 3)
        return scores(*(self.counts @ x for x in stack))  # each (B,)

    def interval(self, confusions: dict) -> dict[str, list[float]]:
        """{score: [low, high]} for each of SCORES."""
        draws = self._resampled(confusions)
        return {name: _percentiles(draws[name]) for name in SCORES}

    def summary(self, confusions: dict) -> dict:
        """The pooled summary of per-scenario confusions, with `ci95`, the number of scenarios and their counts
        (`per_scenario`, so later comparisons across runs can be paired: see confusions_of)."""
        return {
            **pooled(confusions).summary(),
            "scenarios": len(self.scenarios),
            "ci95": self.interval(confusions),
            "per_scenario": {k: confusions[k].counts() for k in self.scenarios},
        }

    def difference(self, run: dict, reference: dict) -> dict[str, dict]:
        """{score: {"delta": run - reference, "ci95": [low, high]}}, paired over the same resampled scenarios."""
        a, b = self._resampled(run), self._resampled(reference)
        sa, sb = pooled(run).summary(), pooled(reference).summary()
        return {
            name: {"delta": point(sa, name) - point(sb, name), "ci95": _percentiles(a[name] - b[name])}
            for name in SCORES
        }

    def ratio(self, run: dict, full: dict, base: dict, score: str = "co3sop-code") -> dict:
        """{"ratio": (run - base) / (full - base), "ci95": [low, high]}: the share of full's gain over base that run
        keeps (a codec against the lossless one and no collaborator), paired over the same resampled scenarios."""
        return self.gain_ratio(run, base, full, base, score)

    def gain_ratio(self, run: dict, run_base: dict, full: dict, base: dict, score: str = "co3sop-code") -> dict:
        """{"ratio": (run - run_base) / (full - base), "ci95": [low, high]}: run's gain over its own base as a share
        of full's over base (another model's collaboration against the reference's), paired over the same resampled
        scenarios."""
        a, ab, f, b = (self._resampled(c)[score] for c in (run, run_base, full, base))
        pa, pab, pf, pb = (point(pooled(c).summary(), score) for c in (run, run_base, full, base))
        with np.errstate(divide="ignore", invalid="ignore"):
            return {
                "ratio": (pa - pab) / (pf - pb) if pf != pb else float("nan"),
                "ci95": _percentiles((a - ab) / (f - b)),
            }


def confusions_of(summary: dict) -> dict[str, Confusion]:
    """Per-scenario confusions back from a Bootstrap.summary() (e.g. read from evaluate's JSON)."""
    return {k: Confusion.from_counts(v) for k, v in summary["per_scenario"].items()}


def _percentiles(values: np.ndarray) -> list[float]:
    values = values[np.isfinite(values)]
    return [float(v) for v in np.percentile(values, [2.5, 97.5])] if len(values) else [float("nan")] * 2


CONVENTIONS_NOTE = (
    "mIoU conventions: co3sop-readme, the mean over all 24 classes with 0 (empty), as the Co3SOP README "
    "reports; co3sop-code, the mean over classes 1..23, as Co3SOP's code computes it; both count a class absent "
    "from truth and prediction ('-') as IoU 0. surroundocc: the mean over the classes 1..23 present in the "
    "truth, and geometry IoU (occupied against empty), as SurroundOcc reports."
)


def markdown_table(results: dict[str, dict], every_class: bool = False) -> str:
    """Per-class IoU (%) and mIoU in the three conventions; one column per named result. every_class: also the rows of
    classes absent everywhere ('-'), which the Co3SOP means count as 0."""
    names = list(results)
    lines = ["| class | " + " | ".join(names) + " |", "|---|" + "---:|" * len(names)]
    for c, cls in enumerate(CLASS_NAMES):
        cells = [results[n]["per_class_iou"][cls] for n in names]
        if all(v is None for v in cells) and not every_class:
            continue
        lines.append(f"| {c} {cls} | " + " | ".join("-" if v is None else f"{100 * v:.2f}" for v in cells) + " |")
    lines.append(
        "| **mIoU co3sop-readme** (24 incl. empty) | "
        + " | ".join(f"**{100 * results[n]['co3sop-readme']['miou']:.2f}**" for n in names)
        + " |"
    )
    lines.append(
        "| **mIoU co3sop-code** (1..23) | "
        + " | ".join(f"**{100 * results[n]['co3sop-code']['miou']:.2f}**" for n in names)
        + " |"
    )
    lines.append(
        "| **mIoU surroundocc** (present 1..23) | "
        + " | ".join(f"**{100 * results[n]['surroundocc']['miou']:.2f}**" for n in names)
        + " |"
    )
    lines.append(
        "| IoU geometry (surroundocc) | "
        + " | ".join(f"{100 * results[n]['surroundocc']['iou']:.2f}" for n in names)
        + " |"
    )
    if all("ci95" in results[n] for n in names):
        for score in SCORES:
            lines.append(
                f"| 95 % interval {score} | " + " | ".join(_span(results[n]["ci95"][score]) for n in names) + " |"
            )
        lines.append("| scenarios | " + " | ".join(str(results[n]["scenarios"]) for n in names) + " |")
    return "\n".join(lines)


def _span(low_high: list[float]) -> str:
    low, high = low_high
    return f"[{100 * low:.2f}, {100 * high:.2f}]"


def difference_table(differences: dict[str, dict], reference: str) -> str:
    """Paired differences (points of IoU, %) against `reference`, with 95 % intervals; one row per run."""
    lines = [f"| against {reference} | " + " | ".join(f"Δ {s}" for s in SCORES) + " |", "|---|" + "---:|" * len(SCORES)]
    for name, diff in differences.items():
        cells = [f"{100 * diff[s]['delta']:+.2f} {_span(diff[s]['ci95'])}" for s in SCORES]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
