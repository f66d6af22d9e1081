"""`python -m nak_training`: train, export and evaluate networks for nak, and report on them.

python -m nak_training all --config training/configs/pointnet-reg.toml --data DATA
python -m nak_training train|export|evaluate --config C --data DATA
python -m nak_training train --config C --data DATA --more-data DATA2 DATA3   (sets of other seeds join train)
python -m nak_training forms --config C --data DATA     (a reduced network's shipping forms, timed)
python -m nak_training report --data DATA
python -m nak_training failures --data DATA    (nonlinear failures against how deep the grasps push)
python -m nak_training forces --data DATA --model DIR   (grasp forces against the FEM's, and their cost)
python -m nak_training misses --data DATA --model DIR   (a network's error against how deep the grasps push)
python -m nak_training paired --data DATA --model A B   (two models' DCMs on the same samples, paired)
python -m nak_training fold --model DIR...    (fold the fixed sizes of graphs exported before export did)
python -m nak_training serve-form --model DIR...    (grasp-encoder graphs rewritten in their served form)
"""

from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path

from .config import TrainConfig, load_config
from .dataset import open_dataset
from .errors import TrainingInputError
from .served import Nak

DEFAULT_MODELS = Path("models/phantom-liver")
DEFAULT_MESH = Path("models/phantom-liver/liver.msh")
DEFAULT_NAK = Path("target/release/nak")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m nak_training", description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    for name, text in [
        ("train", "train (resumes from the run's checkpoint)"),
        ("export", "export the best checkpoint to ONNX + manifest + config"),
        ("evaluate", "score the exported model with nak eval; write its [metrics]"),
        ("all", "train, export and evaluate"),
        ("forms", "export a reduced network as f32 and f16 basis files and folded into the graph; time each"),
    ]:
        command = commands.add_parser(name, help=text)
        command.add_argument("--config", type=Path, required=True, help="training configuration (TOML)")
        command.add_argument("--data", type=Path, required=True, help="a dataset made by nak datagen")
        command.add_argument("--runs", type=Path, default=Path("out/runs"), help="checkpoints and logs")
        command.add_argument("--out", type=Path, default=DEFAULT_MODELS, help="where model directories go")
        command.add_argument(
            "--nak", type=Path, default=DEFAULT_NAK, help="the nak binary (evaluate, Green's-function priors)"
        )
        command.add_argument("--mesh", type=Path, default=DEFAULT_MESH, help="the dataset's mesh (evaluate)")
        command.add_argument("--steps", type=int, help="override the configuration's step count")
        command.add_argument(
            "--split",
            default="test",
            choices=["train", "val", "test", "all"],
            help="the samples of --data evaluate scores on (all: a held-out set of another seed)",
        )
        command.add_argument(
            "--train-samples", type=int, help="train on this many samples (a learning curve's point; name gets -nN)"
        )
        if name in ("train", "all"):
            command.add_argument(
                "--more-data",
                type=Path,
                nargs="+",
                default=[],
                help="sets of other seeds (same mesh and law) whose every sample joins the train split",
            )
    report = commands.add_parser("report", help="the results table and the accuracy-latency figure")
    report.add_argument("--data", type=Path, required=True, help="the linear dataset the models were scored on")
    report.add_argument(
        "--nonlinear-data", type=Path, help="the held-out nonlinear set the nonlinear networks are scored on (Table 3)"
    )
    report.add_argument("--models", type=Path, nargs="+", default=[DEFAULT_MODELS], help="model directories")
    report.add_argument("--nak", type=Path, default=DEFAULT_NAK)
    report.add_argument("--mesh", type=Path, default=DEFAULT_MESH)
    report.add_argument("--out", type=Path, default=Path("docs/reports/models"))
    failures = commands.add_parser("failures", help="a nonlinear dataset's failure rate by the grasps' inward push")
    failures.add_argument("--data", type=Path, required=True, help="a nonlinear dataset made by nak datagen")
    forces = commands.add_parser("forces", help="learned grasp forces and green-tangent's against the FEM's")
    forces.add_argument("--data", type=Path, required=True, help="a nonlinear dataset made by nak datagen")
    forces.add_argument("--model", type=Path, nargs="+", required=True, help="model directories with [forces]")
    forces.add_argument("--nak", type=Path, default=DEFAULT_NAK)
    forces.add_argument("--mesh", type=Path, default=DEFAULT_MESH)
    forces.add_argument("--out", type=Path, default=Path("docs/reports/forces"))
    forces.add_argument(
        "--runs", type=Path, default=Path("out/runs"), help="the models' runs (the head's cost is timed against them)"
    )
    forces.add_argument("--prior", default="green-tangent", choices=["green-tangent", "green-linear"])
    missed = commands.add_parser("misses", help="a network's error by how deep the grasps push, sample by sample")
    missed.add_argument("--data", type=Path, required=True, help="a nonlinear dataset (every sample is scored)")
    missed.add_argument("--model", required=True, help="a model directory, or kelvinlet, green-linear or green-tangent")
    missed.add_argument("--nak", type=Path, default=DEFAULT_NAK)
    missed.add_argument("--mesh", type=Path, default=DEFAULT_MESH)
    missed.add_argument("--figure", type=Path, help="also draw every sample's error against its push (PNG)")
    pair = commands.add_parser("paired", help="two models on the same samples: the DCM gain and its paired error")
    pair.add_argument("--data", type=Path, required=True, help="a dataset made by nak datagen")
    pair.add_argument("--model", nargs=2, required=True, help="two model directories or served names (A, then B)")
    pair.add_argument("--split", default="all", choices=["train", "val", "test", "all"])
    pair.add_argument("--nak", type=Path, default=DEFAULT_NAK)
    pair.add_argument("--mesh", type=Path, default=DEFAULT_MESH)
    refold = commands.add_parser(
        "fold", help="fold the fixed sizes of reduced networks' graphs exported before export did it (in place)"
    )
    refold.add_argument("--model", type=Path, nargs="+", required=True, help="model directories")
    served = commands.add_parser(
        "serve-form",
        help="rewrite grasp-encoder networks' graphs in their served form, faster for one request "
        "(in place; answers checked unchanged)",
    )
    served.add_argument("--model", type=Path, nargs="+", required=True, help="model directories")
    args = parser.parse_args(argv)
    try:
        if args.command == "forces":
            from .force_report import write_force_report

            written = write_force_report(args.data, args.model, args.nak, args.mesh, args.out, args.runs, args.prior)
            print(f"wrote {written}")
            return 0
        if args.command == "failures":
            from .failures import report as failure_report

            print(failure_report(args.data))
            return 0
        if args.command == "misses":
            from .misses import report as misses_report

            print(misses_report(args.data, args.model, args.nak, args.mesh, args.figure))
            return 0
        if args.command == "paired":
            from .paired import report as paired_report

            print(paired_report(args.data, args.model, args.nak, args.mesh, args.split))
            return 0
        if args.command == "fold":
            from .static_sizes import refold_interaction_graph

            for directory in args.model:
                print(refold_interaction_graph(directory))
            return 0
        if args.command == "serve-form":
            from .reform import reform

            for directory in args.model:
                print(reform(directory))
            return 0
        if args.command == "report":
            from .report import write_report

            write_report(args.data, args.models, args.nak, args.mesh, args.out, args.nonlinear_data)
            return 0
        overrides: dict[str, object] = {"steps": args.steps} if args.steps else {}
        if args.train_samples:
            name = load_config(args.config).name
            overrides.update(train_samples=args.train_samples, name=f"{name}-n{args.train_samples}")
        config = load_config(args.config, overrides)
        run(args.command, config, args)
    except TrainingInputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted: run the same command again to resume from the last checkpoint", file=sys.stderr)
        return 130
    return 0


def run(command: str, config: TrainConfig, args: argparse.Namespace) -> None:
    dataset = open_dataset(args.data)
    if command in ("train", "all"):
        from .reduced_train import ReducedTrainer
        from .train import Trainer

        run_dir = args.runs / config.name
        run_dir.mkdir(parents=True, exist_ok=True)
        trainer = ReducedTrainer if config.reduced else Trainer
        training_data = dataset.joined([open_dataset(path) for path in args.more_data])
        log = functools.partial(print, flush=True)
        trainer(config, training_data, run_dir, log=log, nak=Nak(args.nak, args.mesh)).run()
    if command in ("export", "all"):
        from .export import export

        export(config, dataset, args.runs / config.name, args.out)
    if command == "forms":
        from .evaluate import compare_forms

        compare_forms(config, dataset, args.runs / config.name, args.runs / "forms", args.nak, args.mesh)
    if command in ("evaluate", "all"):
        from .evaluate import evaluate

        metrics = evaluate(args.out / config.name, args.data, args.nak, args.mesh, args.split)
        print(f"{config.name}: [metrics] written: {metrics}")
