"""Training: Base, +Res (Method 1) and +Reg (Method 2) on a nak dataset, seeded and resumable.

Per step a batch of samples from p is drawn from the train split; the loss is the L2(Ω) misfit
(lumped nodal volumes, docs/design.md §6) on `query_nodes` nodes drawn uniformly, in normalized output
units. +Res learns u_true − prior; +Reg adds λ_reg × the misfit to the Kelvinlet field on fresh
q samples. Row-wise networks run their encoder over the nodes at rest once per step
(`SetNet.forward_split`), so a step costs O(N + B·(K + Q)) rather than O(B·N). Model selection is on
the val split's volume-weighted DCM, evaluated with the full forward that is exported.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from .config import TrainConfig
from .dataset import Dataset, Mesh, Split, join
from .errors import TrainingInputError
from .kelvinlet import Prior, pad_points
from .models import Grasped, SetNet, build, parameter_count
from .revision import git_commit
from .served import Nak, served_fields
from .sampling import QSampler

EPSILON_GRID_M = (0.01, 0.015, 0.02, 0.025, 0.03, 0.04, 0.05, 0.06, 0.08)
FIT_SAMPLES = 400
STN_PENALTY = 0.01
PROGRESS_EVERY = 50
KELVINLET = "kelvinlet"


def prior_of(mesh: Mesh, epsilon: float) -> Prior:
    nu, _, lam = mesh.prior
    return Prior(nu, epsilon, lam)


def prior_fields(prior: Prior, mesh: Mesh, split: Split, batch: int = 16) -> torch.Tensor:
    """The prior over every node for every sample of `split`: f32 [S, N, 3]."""
    out = torch.empty_like(split.fields)
    for start in range(0, len(split), batch):
        chunk = split.samples[start : start + batch]
        _, points, disp, mask = pad_points(
            mesh.positions,
            [torch.from_numpy(s.nodes) for s in chunk],
            [torch.from_numpy(s.displacements) for s in chunk],
        )
        out[start : start + len(chunk)] = prior.evaluate(mesh.positions, points, disp, mask).float()
    return out


def relative_errors(truth: torch.Tensor, estimate: torch.Tensor, volumes: torch.Tensor) -> torch.Tensor:
    """‖u_true − û‖_{L2(Ω)} / ‖u_true‖_{L2(Ω)} per sample (docs/design.md §6), truth/estimate [S, N, 3]."""
    v = volumes.to(torch.float64)
    err = ((truth.double() - estimate.double()) ** 2).sum(-1) @ v
    norm = (truth.double() ** 2).sum(-1) @ v
    return (err / norm).sqrt()


def dcm(truth: torch.Tensor, estimate: torch.Tensor, volumes: torch.Tensor) -> float:
    return float(100.0 * (1.0 - relative_errors(truth, estimate, volumes).mean()))


def spread(split: Split, count: int) -> Split:
    """`count` samples spread evenly over `split` (single-grasper samples come first in a dataset)."""
    keep = torch.linspace(0, len(split) - 1, min(count, len(split))).round().long().unique()
    return split.pick(keep.tolist())


def fit_epsilon(mesh: Mesh, train: Split, log: Any = print) -> tuple[float, dict[str, float]]:
    """The grid ε whose prior scores best on (FIT_SAMPLES spread over) the train split."""
    subset = spread(train, FIT_SAMPLES)
    scores = {}
    for eps in EPSILON_GRID_M:
        scores[f"{eps:g}"] = dcm(subset.fields, prior_fields(prior_of(mesh, eps), mesh, subset), mesh.nodal_volumes)
        log(f"  ε = {eps * 100:4.1f} cm: prior DCM {scores[f'{eps:g}']:7.2f} % on {len(subset)} train samples")
    best = max(EPSILON_GRID_M, key=lambda e: scores[f"{e:g}"])
    return best, scores


@dataclass
class Batch:
    """Normalized features of a batch, laid out for `SetNet.forward_split`."""

    dense: torch.Tensor  # [B, N, 7]
    rows: torch.Tensor  # [B, K, 7], the grasped rows
    grasped: Grasped


class Run:
    """What every training run shares: seeds, the train/val splits, the prior's ε (fitted once and kept
    in state.json), AdamW with warm-up and cosine decay, progress with ETA, model selection on val,
    checkpoints and resume. Subclasses build `self.model` and define a step and the val score.

    The sets `dataset.more` (other seeds) add every sample to the train split; val and test stay the
    dataset's own, so that runs with and without them are selected and compared on the same samples."""

    model: torch.nn.Module

    def __init__(
        self, config: TrainConfig, dataset: Dataset, run_dir: Path, log: Any = print, nak: Nak | None = None
    ) -> None:
        self.config, self.dataset, self.run_dir, self.log, self.nak = config, dataset, run_dir, log, nak
        if dataset.more and config.method == "res" and config.prior != KELVINLET:
            # nak writes a served prior's fields per split of one set (served.py); joined sets have no such split.
            raise TrainingInputError(
                dataset.more[0].root,
                f"more data is not supported with the {config.prior} prior (served by nak per split of one set)",
            )
        torch.set_num_threads(config.threads)
        torch.manual_seed(config.seed)
        self.mesh = dataset.mesh
        self.generator = torch.Generator().manual_seed(config.seed)
        # A set still being made is read as it stood now; its summary names the chunks it had.
        self.chunks = dataset.complete_chunks()
        # Each added set with the chunks it had, read as it stood now like the first.
        self.more = [(m, m.complete_chunks()) for m in dataset.more]
        self.val, own_train = self._own_splits()
        own = [(dataset, own_train, self.chunks)]
        own += [(m, m.load("all", config.subsets, chunks), chunks) for m, chunks in self.more]
        self.train = join([split for _, split, _ in own])
        if config.train_samples:
            self.train = spread(self.train, config.train_samples)
        # Load-path states come after the samples they lead to (the POD takes the samples alone).
        self.sample_count = len(self.train)
        if config.path_states_from < 1.0:
            kept = {id(s) for s in self.train.samples}
            states = [
                d.load_path_states([s for s in split.samples if id(s) in kept], chunks, config.path_states_from)
                for d, split, chunks in own
            ]
            self.train = join([self.train, *(s for s in states if s is not None)])
        self.log(
            f"{config.name}: {config.architecture} ({config.size}) {config.method}, {len(self.train)} train / "
            f"{len(self.val)} val samples ({config.subset}), mesh {self.mesh.name} {self.mesh.node_count} nodes"
        )
        if config.holdout == "val":
            self.log(f"  train takes every sample of {dataset.root} but the {len(self.val)} val samples (holdout)")
        for m, c in self.more:
            self.log(f"  train adds every sample of {m.root} (seed {m.seed}, {len(c)} of {m.chunk_count()} chunks)")
        if config.path_states_from < 1.0:
            self.log(
                f"  of which {self.path_states} are the converged load steps (at {config.path_states_from:g} of "
                "the grasp or more) of the train samples"
            )
        state = self._load_state()
        if state is None:
            if config.epsilon == "fit":
                self.log("fitting ε on the train split:")
                alone = Split(self.train.samples[: self.sample_count], self.train.fields[: self.sample_count])
                epsilon, scores = fit_epsilon(self.mesh, alone, self.log)
            else:
                epsilon, scores = float(config.epsilon), {}
            state = {"epsilon": epsilon, "epsilon_scores": scores}
            (run_dir / "state.json").write_text(json.dumps(state, indent=2) + "\n")
        self.epsilon = float(state["epsilon"])
        self.prior = prior_of(self.mesh, self.epsilon)
        self.log(f"prior: ν = {self.prior.poisson_ratio}, ε = {self.epsilon * 100:g} cm, λ = {self.prior.lam:g}")
        if config.method == "res" and config.prior != KELVINLET:
            self.log(f"prior of the residual: {config.prior}, through Green's functions as nak serves it")
        self.volumes = self.mesh.nodal_volumes.float()
        self.q = QSampler(self.mesh, self.generator) if config.method == "reg" else None

    @property
    def path_states(self) -> int:
        """How many of the train split's entries are load-path states rather than samples."""
        return len(self.train) - self.sample_count

    def residual_prior(self, split: Split, name: str) -> torch.Tensor:
        """The prior +Res learns its residual to, for every sample of `split` (drawn from split `name`):
        the Kelvinlet at the run's ε, or the field nak serves as green-linear or green-tangent. f32 [S, N, 3]."""
        prior = self.config.prior
        if prior == KELVINLET:
            return prior_fields(self.prior, self.mesh, split, batch=64)
        if self.nak is None:
            raise TrainingInputError(self.dataset.root, f"the {prior} prior needs the nak binary (--nak)")
        self.log(f"{prior} over the {name} split ({len(split)} samples), through nak…")
        return served_fields(self.nak, self.dataset, name, split, prior, self.run_dir)

    def _start(self, model: torch.nn.Module) -> None:
        """Takes `model` for training and resumes from the run's checkpoint if there is one."""
        self.model = model
        self.optimizer = torch.optim.AdamW(model.parameters(), lr=self.config.lr, weight_decay=self.config.weight_decay)
        # With `ema`, the moving average of the weights is what is validated, kept and exported.
        self.ema: dict[str, torch.Tensor] | None = (
            {k: v.detach().clone() for k, v in model.state_dict().items()} if self.config.ema else None
        )
        self.step = 0
        self.best = -math.inf
        self.elapsed = 0.0
        self.history: list[dict[str, float]] = []
        self._resume()

    def _step(self) -> float:
        raise NotImplementedError

    def _descend(self, loss: torch.Tensor) -> float:
        """One optimizer step on `loss` at the schedule's learning rate; returns the loss."""
        for group in self.optimizer.param_groups:
            group["lr"] = self._learning_rate()
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        if self.ema is not None:
            self._average()
        return float(loss.detach())

    @torch.no_grad()
    def _average(self) -> None:
        """Moves the exponential moving average of the weights (Polyak averaging) towards this step's:
        an average over the last ~1/(1 − ema) steps, which damps the noise of small batches that a
        network fitting few samples otherwise ends on. Early steps weigh more (the usual warm-up)."""
        assert self.ema is not None
        decay = min(self.config.ema, (1 + self.step) / (10 + self.step))
        for name, value in self.model.state_dict().items():
            if value.is_floating_point():
                self.ema[name].lerp_(value, 1.0 - decay)
            else:
                self.ema[name].copy_(value)

    def _score(self) -> float:
        """The val DCM of the weights that would be kept: the moving average with `ema`, else the model's."""
        if self.ema is None:
            return self.validate()
        trained = {k: v.clone() for k, v in self.model.state_dict().items()}
        self.model.load_state_dict(self.ema)
        try:
            return self.validate()
        finally:
            self.model.load_state_dict(trained)

    def validate(self) -> float:
        raise NotImplementedError

    # -- set-up ---------------------------------------------------------------------------------

    def _load_state(self) -> dict[str, Any] | None:
        path = self.run_dir / "state.json"
        if not path.is_file():
            return None
        try:
            state: dict[str, Any] = json.loads(path.read_text())
            return state
        except json.JSONDecodeError as e:
            raise TrainingInputError(path, f"unreadable ({e}); delete the run directory to start over") from e

    def _resume(self) -> None:
        path = self.run_dir / "checkpoint.pt"
        if not path.is_file():
            return
        try:
            checkpoint = torch.load(path, weights_only=False)
        except Exception as e:  # torch raises many types for a truncated or foreign file
            raise TrainingInputError(path, f"unreadable checkpoint ({e}); delete it to start over") from e
        if checkpoint.get("config") != self.config.to_dict():
            raise TrainingInputError(path, "was written with another configuration; use a new run directory")
        if checkpoint.get("mesh_hash") != self.mesh.content_hash:
            raise TrainingInputError(
                path, f"was trained on mesh {checkpoint.get('mesh_hash')}; this dataset is {self.mesh.content_hash}"
            )
        trained_on, here = checkpoint.get("data"), self._data_description()
        if trained_on is not None and trained_on != here:
            raise TrainingInputError(
                path,
                f"was trained on {describe_data(trained_on)}; {self.dataset.root} gives {describe_data(here)}: a run "
                "is not resumed on another set (use a new run directory)",
            )
        trained_law = self.dataset.law_of_run(checkpoint)
        if trained_law != self.dataset.volumetric_law:
            raise TrainingInputError(
                path,
                f"was trained on data solved under the volumetric law {trained_law}; {self.dataset.root} was "
                f"solved under {self.dataset.volumetric_law}: data of two laws is not mixed (use a new run directory)",
            )
        self.model.load_state_dict(checkpoint["model"])
        if self.ema is not None:
            self.ema = checkpoint["ema"]
        self.optimizer.load_state_dict(checkpoint["optimizer"])
        self.generator.set_state(checkpoint["generator"])
        self.step, self.best, self.elapsed = checkpoint["step"], checkpoint["best"], checkpoint["elapsed"]
        self.history = checkpoint["history"]
        self.log(f"resumed at step {self.step} (best val DCM {self.best:.2f} %)")

    # -- the schedule ---------------------------------------------------------------------------

    def _learning_rate(self) -> float:
        warmup = min(100, self.config.steps // 10)
        if self.step < warmup:
            return self.config.lr * (self.step + 1) / warmup
        progress = (self.step - warmup) / max(1, self.config.steps - warmup)
        return self.config.lr * (0.02 + 0.98 * 0.5 * (1.0 + math.cos(math.pi * progress)))

    # -- validation and the loop ----------------------------------------------------------------

    def run(self) -> dict[str, Any]:
        c = self.config
        self.log(f"{parameter_count(self.model):,} parameters; {c.steps} steps of {c.batch} samples")
        self.model.train()
        commit = git_commit()
        started = time.monotonic() - self.elapsed
        window: list[float] = []
        while self.step < c.steps:
            window.append(self._step())
            self.step += 1
            if self.step % PROGRESS_EVERY == 0 or self.step == c.steps:
                self.elapsed = time.monotonic() - started
                rate = self.step / self.elapsed
                eta = (c.steps - self.step) / max(rate, 1e-9)
                self.log(
                    f"step {self.step:>6}/{c.steps}  loss {sum(window) / len(window):.5f}  "
                    f"{rate:5.2f} steps/s  elapsed {_clock(self.elapsed)}  ETA {_clock(eta)}"
                )
                window.clear()
            if self.step % c.val_every == 0 or self.step == c.steps:
                score = self._score()
                improved = score > self.best
                if improved:
                    self.best = score
                    torch.save(self.model.state_dict() if self.ema is None else self.ema, self.run_dir / "best.pt")
                self.history.append({"step": self.step, "val_dcm": score})
                self.elapsed = time.monotonic() - started
                self._checkpoint()
                best = "best so far: saved" if improved else f"best {self.best:.2f} %"
                self.log(f"  val DCM {score:.2f} %  ({best}); checkpoint at step {self.step}")
        summary = {
            "name": c.name,
            "epsilon": self.epsilon,
            "val_dcm": self.best,
            "steps": self.step,
            "training_time_s": round(self.elapsed, 1),
            "commit": commit,
            "volumetric_law": self.dataset.volumetric_law,
            "train_samples": self.sample_count,
            **({"path_states": self.path_states} if self.path_states else {}),
            "val_samples": len(self.val),
            **({"chunks": self.chunks} if len(self.chunks) < self.dataset.chunk_count() else {}),
            **({"more_data": self._more_description()} if self.more else {}),
            "parameters": parameter_count(self.model),
            "history": self.history,
        }
        (self.run_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        return summary

    def _data_description(self) -> dict[str, Any]:
        """What a run's data is, for telling it from another set on resume: seed, size, train samples
        (and the seeds and sizes of the sets that add to it)."""
        info = self.dataset.info
        return {
            "seed": self.dataset.seed,
            "samples": int(info["single"]) + int(info["multi"]),
            "train_samples": self.sample_count,
            **({"path_states": self.path_states} if self.path_states else {}),
            **(
                {"more": [{k: d[k] for k in ("seed", "single", "multi")} for d in self._more_description()]}
                if self.more
                else {}
            ),
        }

    def _own_splits(self) -> tuple[Split, Split]:
        """The dataset's own samples that select the checkpoint (`val_samples` spread over its val split)
        and those that train: its train split, or with holdout = "val" every other sample, read in one
        pass over the chunks."""
        c = self.config
        if c.holdout == "val+test":
            val = spread(self.dataset.load("val", c.subsets, self.chunks), c.val_samples)
            return val, self.dataset.load("train", c.subsets, self.chunks)
        own = self.dataset.load("all", c.subsets, self.chunks)
        val = spread(own.pick([i for i, s in enumerate(own.samples) if s.split == "val"]), c.val_samples)
        selecting = {s.index for s in val.samples}
        rest = [i for i, s in enumerate(own.samples) if s.index not in selecting]
        # Train, then test, then val samples, as runs before this one pass read them.
        return val, own.pick(sorted(rest, key=lambda i: ("train", "test", "val").index(own.samples[i].split)))

    def _more_description(self) -> list[dict[str, Any]]:
        """Each added set as the manifest records it: where, seed, size, and the chunks it had if
        it was still being made (to retrain on the same samples)."""
        return [
            {
                "dataset": str(m.root),
                "seed": m.seed,
                "single": int(m.info["single"]),
                "multi": int(m.info["multi"]),
                **({"chunks": c} if len(c) < m.chunk_count() else {}),
            }
            for m, c in self.more
        ]

    def _checkpoint(self) -> None:
        checkpoint = {
            "config": self.config.to_dict(),
            "mesh_hash": self.mesh.content_hash,
            "data": self._data_description(),
            "volumetric_law": self.dataset.volumetric_law,
            "model": self.model.state_dict(),
            "ema": self.ema,
            "optimizer": self.optimizer.state_dict(),
            "generator": self.generator.get_state(),
            "step": self.step,
            "best": self.best,
            "elapsed": self.elapsed,
            "history": self.history,
        }
        tmp = self.run_dir / "checkpoint.pt.partial"
        torch.save(checkpoint, tmp)
        tmp.replace(self.run_dir / "checkpoint.pt")


def describe_data(data: dict[str, Any]) -> str:
    more = "".join(
        f" and all of a {m['single'] + m['multi']}-sample set of seed {m['seed']}" for m in data.get("more", [])
    )
    return f"{data['train_samples']} train samples of a {data['samples']}-sample set of seed {data['seed']}{more}"


class Trainer(Run):
    """A full-field network (PointNet, DeepSet U-Net, ISAB): features of every node in, field out."""

    model: SetNet

    def __init__(
        self, config: TrainConfig, dataset: Dataset, run_dir: Path, log: Any = print, nak: Nak | None = None
    ) -> None:
        super().__init__(config, dataset, run_dir, log, nak)
        residual = config.method == "res"
        self.train_prior = self.residual_prior(self.train, "train") if residual else None
        self.val_prior = self.residual_prior(self.val, "val") if residual else None
        model = build(config.architecture, config.size, self.mesh)
        self._set_statistics(model)
        positions = self.mesh.positions.float()
        rest = torch.cat([positions, torch.zeros(self.mesh.node_count, 4)], dim=1)
        self.rest = model.normalizer.inputs(rest)
        self._start(model)

    def _set_statistics(self, model: SetNet) -> None:
        """Input and output normalization from the train split (they become part of the graph)."""
        positions = self.mesh.positions
        u = torch.cat([torch.from_numpy(s.displacements) for s in self.train.samples])
        target = self.train.fields if self.train_prior is None else self.train.fields - self.train_prior
        flat = target.reshape(-1, 3).double()
        model.normalizer.set(
            x_mean=positions.mean(0),
            x_std=positions.std(0),
            u_scale=(u**2).mean(0).sqrt(),
            out_mean=flat.mean(0),
            out_std=flat.std(0),
        )

    def _batch(self, nodes: list[torch.Tensor], displacements: list[torch.Tensor]) -> Batch:
        ids, _, disp, mask = pad_points(self.mesh.positions, nodes, displacements)
        # Padding repeats a sample's first grasped node: give it that node's displacement too, so the
        # repeated row is identical wherever it is written.
        disp = torch.where(mask[..., None], disp, disp[:, :1])
        b = len(nodes)
        rows = torch.cat([disp.float() / self.model.normalizer.u_scale, torch.ones(b, ids.shape[1], 1)], dim=-1)
        dense = self.rest.expand(b, -1, -1).clone()
        dense[torch.arange(b).unsqueeze(-1).expand_as(ids), ids, 3:7] = rows
        grasped = dense.gather(1, ids.unsqueeze(-1).expand(-1, -1, 7))
        return Batch(dense, grasped, Grasped(ids, mask))

    def _predict(self, batch: Batch, query: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if self.model.row_wise:
            out = self.model.forward_split(self.rest, batch.rows, batch.grasped, batch.dense[:, query])
            return out, torch.zeros(())
        out, penalty = self.model.forward_normalized(batch.dense)
        return out[:, query], penalty

    def _misfit(self, prediction: torch.Tensor, target: torch.Tensor, query: torch.Tensor) -> torch.Tensor:
        """Volume-weighted mean squared misfit in normalized output units."""
        n = self.model.normalizer
        weights = self.volumes[query] / self.volumes[query].mean()
        squared = ((prediction - (target - n.out_mean) / n.out_std) ** 2).sum(-1)
        return (squared * weights).mean()

    def _step(self) -> float:
        c = self.config
        g = self.generator
        picks = torch.randint(len(self.train), (c.batch,), generator=g)
        samples = [self.train.samples[int(i)] for i in picks]
        nodes = [torch.from_numpy(s.nodes) for s in samples]
        displacements = [torch.from_numpy(s.displacements) for s in samples]
        query = torch.randperm(self.mesh.node_count, generator=g)[: c.query_nodes]
        rows = (picks[:, None], query[None, :])
        target = self.train.fields[rows]
        if self.train_prior is not None:
            target = target - self.train_prior[rows]
        if self.q is not None:
            # q samples ride in the same forward pass: the nodes at rest are encoded once for both.
            q_nodes, q_displacements = self.q.draw(c.q_batch)
            _, points, disp, mask = pad_points(self.mesh.positions, q_nodes, q_displacements)
            kelvinlet = self.prior.evaluate(self.mesh.positions[query], points, disp, mask).float()
            nodes, displacements = nodes + q_nodes, displacements + q_displacements
        prediction, penalty = self._predict(self._batch(nodes, displacements), query)
        loss = self._misfit(prediction[: c.batch], target, query) + STN_PENALTY * penalty
        if self.q is not None:
            loss = loss + c.lambda_reg * self._misfit(prediction[c.batch :], kelvinlet, query)
        return self._descend(loss)

    @torch.no_grad()
    def validate(self, batch: int = 8) -> float:
        """Volume-weighted DCM of the served field (prior added for +Res, held nodes answered exactly)
        on the val samples."""
        self.model.eval()
        estimates = torch.empty_like(self.val.fields)
        for start in range(0, len(self.val), batch):
            chunk = self.val.samples[start : start + batch]
            features = served_features(self.mesh, [s.nodes for s in chunk], [s.displacements for s in chunk])
            estimates[start : start + len(chunk)] = self.model(features)
        if self.val_prior is not None:
            estimates += self.val_prior
        # nak answers each held node with its prescribed displacement (docs/design.md §7).
        for i, s in enumerate(self.val.samples):
            estimates[i, torch.from_numpy(s.nodes)] = torch.from_numpy(s.displacements).to(estimates.dtype)
        self.model.train()
        return dcm(self.val.fields, estimates, self.mesh.nodal_volumes)


def served_features(mesh: Mesh, nodes: list[Any], displacements: list[Any]) -> torch.Tensor:
    """Raw features [B, N, 7] exactly as nak builds them for a request (f32 positions, u_s, a)."""
    b, n = len(nodes), mesh.node_count
    features = torch.zeros(b, n, 7)
    features[:, :, 0:3] = mesh.positions.float()
    for i, (ids, disp) in enumerate(zip(nodes, displacements, strict=True)):
        ids_t = torch.as_tensor(ids, dtype=torch.long)
        features[i, ids_t, 3:6] = torch.as_tensor(disp, dtype=torch.float64).float()
        features[i, ids_t, 6] = 1.0
    return features


def load_trained(run_dir: Path, config: TrainConfig, mesh: Mesh) -> SetNet:
    """The best model of a finished run."""
    path = run_dir / "best.pt"
    if not path.is_file():
        raise TrainingInputError(path, "missing: train the model first")
    model = build(config.architecture, config.size, mesh)
    model.load_state_dict(torch.load(path, weights_only=True))
    model.eval()
    return model


def _clock(seconds: float) -> str:
    seconds = int(seconds)
    return f"{seconds // 3600}:{seconds % 3600 // 60:02d}:{seconds % 60:02d}"
