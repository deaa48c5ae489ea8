"""`calibrate`: measure a LiDAR model's int8 activation ranges on a dataset split and write them into a checkpoint.

    ros2 run co3sop_nodes calibrate --model runs/x/model.pt --data data/bench --splits validate --out model.pt
    ros2 run co3sop_nodes calibrate --model M.pt --data data/bench --splits validate --fine-tune train --out M.pt

With them, `precision int8` (the nodes' parameter, `evaluate`'s and `demo`'s option) computes the model's
SSCNet-style vehicle half and its head's layers up to 1/2 in int8 on the CPU. The ranges minimise each activation's
squared quantization error over every CAV's scan of the splits (the head's on each scan's own features:
inference/calibration.py); calibrate on train or validate, never on test. With --fine-tune, the int8 layers then get
weights of their own, fine-tuned through the int8 arithmetic on those splits toward the float model
(train/quantization_aware.py): the vehicle half's on scans, then the head's on the features the int8 vehicles and
the ego's fusion make (--modules: only some; the others keep --model's). Resumable: run the same command again
after an interruption.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import torch

from co3sop_nodes.cli.common import run
from co3sop_nodes.common.errors import Co3sopError
from co3sop_nodes.common.progress import progress
from co3sop_nodes.inference.calibration import calibrate
from co3sop_nodes.inference.checkpoint import load_model, read_checkpoint, resolve_checkpoint, save_calibrated
from co3sop_nodes.model.path import InferencePath
from co3sop_nodes.train.dataset import OccupancyDataset
from co3sop_nodes.train.quantization_aware import fine_tune_int8, head_example


def main(args: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="calibrate", description=__doc__.split("\n\n")[1])
    parser.add_argument("--model", required=True, help="a checkpoint file, or a shipped model's name")
    parser.add_argument("--data", type=Path, required=True, help="an OPV2V / Co3SOP dataset root")
    parser.add_argument("--splits", nargs="+", default=["validate"], help="the splits whose scans are measured")
    parser.add_argument("--out", type=Path, required=True, help="the calibrated checkpoint (may be --model's file)")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument(
        "--fine-tune", nargs="+", default=[], metavar="SPLIT", help="fine-tune the int8 layers on these"
    )
    parser.add_argument(
        "--modules", nargs="+", metavar="MODULE", help="fine-tune these int8 modules only (vehicle.encoder, ego.head)"
    )
    parser.add_argument("--steps", type=int, default=1500, help="fine-tuning steps of each module (one sample each)")
    parser.add_argument("--lr", type=float, default=1e-4, help="fine-tuning learning rate (Adam)")
    parser.add_argument("--seed", type=int, default=0, help="fine-tuning: the order of the scans")
    opts = parser.parse_args(args)
    for flag, splits in (("--splits", opts.splits), ("--fine-tune", opts.fine_tune)):
        if "test" in splits:
            parser.error(f"{flag} test: the reported split is never used to choose anything; take train or validate")
    if opts.threads < 1:
        parser.error(f"--threads {opts.threads}: at least 1")
    if opts.steps < 1 or not opts.lr > 0:
        parser.error(f"--steps {opts.steps} --lr {opts.lr}: at least one step, a positive rate")
    torch.set_num_threads(opts.threads)
    source = resolve_checkpoint(opts.model, "--model")
    model, _ = load_model(source)
    if model.cfg.modality != "lidar" or not model.int8_activations():
        raise Co3sopError(
            f"--model {opts.model}: {model.cfg.name} is not a LiDAR model with int8 layers (calibrate measures on "
            "scans: an SSCNet-style vehicle half, a convolutional head)"
        )
    unknown = sorted(set(opts.modules or ()) - set(model.int8_modules))
    if unknown:
        raise Co3sopError(
            f"--modules {' '.join(unknown)}: {model.cfg.name}'s int8 modules are {', '.join(model.int8_modules)}"
        )
    dataset = OccupancyDataset(opts.data, opts.splits, model.cfg)
    agents = [(f, j) for f, frame in enumerate(dataset.frames) for j in range(len(frame.cavs))]
    bar = progress(len(agents), "calibrate", "scan")

    def scans():
        for f, j in agents:
            yield torch.from_numpy(dataset.agent(f, j).inputs["occupancy"])[None]
            bar.update(1)

    ranges = calibrate(model, scans())
    bar.close()
    command = shlex.join(["calibrate", *(sys.argv[1:] if args is None else args)])
    made = {"command": command, "data": str(opts.data), "splits": list(opts.splits), "scans": len(agents)}
    weights = {}
    if opts.fine_tune:
        weights, made["fine_tune"] = fine_tune(model, ranges, opts, source)
    save_calibrated(source, opts.out, ranges, made, weights)
    for state in opts.out.parent.glob(f"{opts.out.name}.int8-tuning.*"):
        state.unlink()  # the checkpoint holds what they made
    for name, value in ranges.items():
        print(f"{name}: {value:.4g}")
    for prefix, how in made.get("fine_tune", {}).items():
        print(f"calibrate: {prefix}'s int8 layers fine-tuned on {'+'.join(how['splits'])} ({how['steps']} steps)")
    print(f"calibrate: {len(agents)} scans of {'+'.join(opts.splits)}; wrote {opts.out}")
    return 0


def fine_tune(model, ranges: dict[str, float], opts, source: Path) -> tuple[dict[str, torch.Tensor], dict]:
    """The int8 modules of --modules (default: all) fine-tuned on --fine-tune's splits, the vehicle half first
    (the head learns on the features its int8 path makes), each resumable from a state beside --out; any other
    keeps the int8 weights --model has for it where it has them, tuned for the same ranges. The int8 weights, and
    how each module's were made."""
    modules = list(opts.modules or model.int8_modules)
    previous = read_checkpoint(source).get("int8", {})
    made = previous.get("fine_tune", {})
    if "splits" in made:  # written when only a vehicle half's int8 layers were fine-tuned
        made = {"vehicle.encoder": made}
    made = {p: how for p, how in made.items() if p in model.int8_modules}
    weights = {}
    for prefix, module in model.int8_modules.items():
        own = {n: t for n, t in model.int8_tuned_weights().items() if n.startswith(f"{prefix}.")}
        if prefix in modules or not own:
            continue
        names = [f"{prefix}.{n}" for n in module.ACTIVATIONS]
        if any(previous.get("ranges", {}).get(n) != ranges[n] for n in names):
            raise Co3sopError(
                f"--modules {' '.join(modules)}: --model's int8 weights of {prefix} were fine-tuned for ranges other "
                "than those measured now: fine-tune it too"
            )
        weights.update(own)
    model.calibrate(ranges, weights)
    dataset = OccupancyDataset(opts.data, opts.fine_tune, model.cfg)
    for prefix in [m for m in model.int8_modules if m in modules]:
        if prefix == "vehicle.encoder":
            agents = [(f, j) for f, frame in enumerate(dataset.frames) for j in range(len(frame.cavs))]

            def example(i: int) -> torch.Tensor:
                return torch.from_numpy(dataset.agent(*agents[i]).inputs["occupancy"])[None]

            count = len(agents)
        else:  # on the features the int8 vehicles (as tuned so far) and the int8 ego's fusion make
            deployed = load_model(source)[0].calibrate(ranges, weights).use(InferencePath(precision="int8"))

            def example(i: int) -> tuple[torch.Tensor, torch.Tensor]:
                return head_example(model, deployed, dataset.sample(i))

            count = len(dataset)
        bar = progress(opts.steps, f"fine-tune {prefix}", "step")

        def on_step(step: int, loss: float) -> None:
            bar.set_postfix(loss=f"{loss:.4g}", refresh=False)
            bar.update(step + 1 - bar.n)  # a resumed run starts past 0

        state = opts.out.with_name(f"{opts.out.name}.int8-tuning.{prefix}")
        weights.update(fine_tune_int8(model, prefix, example, count, opts.steps, opts.lr, opts.seed, state, on_step))
        bar.close()
        made[prefix] = {"splits": list(opts.fine_tune), "steps": opts.steps, "lr": opts.lr, "seed": opts.seed}
    return weights, made


entry = run(main)
