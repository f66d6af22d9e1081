"""The training package (training/nak_training) against nak itself: its Kelvinlet equals the served
prior, its datasets are nak's own files, bad input is refused by name, an interrupted run resumes to the
same weights, and a tiny end-to-end run (datagen → train → export → nak serve) serves what onnxruntime
computes and beats the untrained network."""

from __future__ import annotations

import json
import shutil
import subprocess
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import client
import grpc
import numpy as np
import onnx
import onnxruntime
import pytest
import torch
from safetensors.numpy import load_file
from conftest import ROOT, start_server
from nak_training.config import load_config, parse_config
from nak_training.dataset import Sample, open_dataset
from nak_training.errors import TrainingInputError
from nak_training.evaluate import evaluate, nak_eval
from nak_training.export import export
from nak_training.force_report import by_direction, field_only, push_cosines, write_force_report
from nak_training.kelvinlet import Prior, pad_points
from nak_training.models import Grasped, MeshGNN, build
from nak_training.grasp_served import ServedGraspNet
from nak_training.reduced import Encoder, Ensemble, GraspEncoder, InteractionGraph, ReducedNet, project, weighted_basis
from nak_training.reduced_train import HeldNodes, ReducedTrainer, interaction_batch, interaction_input, load_reduced
from nak_training.reform import batch_is_fixed, reform
from nak_training.served import Nak
from nak_training.static_sizes import fold_static_sizes, refold_interaction_graph
from nak_training.train import Trainer

COARSE = ROOT / "models" / "phantom-liver" / "liver-coarse.msh"


def coarse_set(nak_binary: Path, out: Path, single: int, multi: int, seed: int, chunk_size: int) -> Path:
    """A small linear dataset on the coarse phantom, as `nak datagen` writes it."""
    command = [str(nak_binary), "datagen", "--mesh", str(COARSE), "--regime", "linear", "--single", str(single)]
    command += ["--multi", str(multi), "--seed", str(seed), "--out", str(out), "--chunk-size", str(chunk_size)]
    subprocess.run(command, check=True, capture_output=True)
    return out


@pytest.fixture(scope="module")
def coarse_data(nak_binary: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return coarse_set(nak_binary, tmp_path_factory.mktemp("data") / "coarse", 60, 40, seed=3, chunk_size=50)


def tiny_config(**overrides: Any) -> dict[str, Any]:
    values = dict(name="tiny", architecture="pointnet", method="res", epsilon=0.02, steps=6, batch=4)
    values.update(query_nodes=256, val_every=3, val_samples=8, threads=2, lr=3e-3)
    return {**values, **overrides}


def quiet(_: str) -> None:
    pass


def test_python_prior_equals_the_served_prior(nak_binary: Path, coarse_data: Path) -> None:
    mesh = open_dataset(coarse_data).mesh
    prior = Prior(*mesh.prior)
    pb, rpc = client.load_stubs()
    with start_server(nak_binary, ["--mesh", str(COARSE)]) as address, grpc.insecure_channel(address) as channel:
        stub = rpc.DeformationStub(channel)
        sets = {s.name: list(s.nodes) for s in stub.GetMesh(pb.GetMeshRequest()).node_sets}
        cases = [
            [(sets["grasp_02"][:1], (0.0, 0.03, 0.0))],
            [(sets["grasp_05"][:6], (0.02, -0.01, 0.04))],
            [(sets["grasp_03"][:8], (0.01, 0.03, -0.01)), (sets["grasp_08"][:5], (-0.05, 0.02, 0.015))],
        ]
        for grasps in cases:
            request = pb.PredictRequest(
                model="kelvinlet",
                grasps=[pb.Grasp(nodes=n, displacement=pb.Vec3(x=u[0], y=u[1], z=u[2])) for n, u in grasps],
            )
            served = np.frombuffer(stub.Predict(request).displacements, dtype="<f4").reshape(-1, 3)
            nodes = torch.tensor([n for ns, _ in grasps for n in ns])
            disp = torch.tensor([u for ns, u in grasps for _ in ns], dtype=torch.float64)
            _, points, u, mask = pad_points(mesh.positions, [nodes], [disp])
            ours = prior.evaluate(mesh.positions, points, u, mask)[0].numpy()
            # λ lets several points miss their displacement slightly; nak answers held nodes exactly.
            ours[nodes.numpy()] = disp.numpy()
            relative = np.linalg.norm(ours - served) / np.linalg.norm(served)
            assert relative < 1e-5, f"{len(nodes)} points: relative difference {relative:.2e}"


def test_split_forward_equals_the_full_forward_for_every_row_wise_network() -> None:
    torch.manual_seed(0)
    n, b, k = 300, 3, 6
    rest = torch.randn(n, 7)
    rest[:, 3:] = 0
    ids = torch.stack([torch.randperm(n)[:k] for _ in range(b)])
    mask = torch.ones(b, k, dtype=torch.bool)
    mask[1, 4:] = False
    ids[1, 4:] = ids[1, 0]  # padding repeats a real row, as pad_points does
    dense = rest.expand(b, -1, -1).clone()
    for i in range(b):
        real = ids[i, : int(mask[i].sum())]
        dense[i, real, 3:6] = torch.randn(len(real), 3)
        dense[i, real, 6] = 1.0
    rows = dense.gather(1, ids.unsqueeze(-1).expand(-1, -1, 7))
    for architecture in ("pointnet", "deepset", "isab"):
        model = build(architecture, "cpu").eval()
        assert model.row_wise
        full, _ = model.forward_normalized(dense)
        split = model.forward_split(rest, rows, Grasped(ids, mask), dense)
        assert torch.allclose(full, split, atol=1e-5), architecture
    for architecture in ("pointnet", "deepset", "isab"):
        model = build(architecture, "paper").eval()
        out, _ = model.forward_normalized(dense[:1])
        assert out.shape == (1, n, 3)


def test_a_variant_configuration_names_only_what_it_changes(tmp_path: Path) -> None:
    (tmp_path / "base.toml").write_text('name = "base"\narchitecture = "pod"\nmethod = "base"\nsteps = 40\n')
    (tmp_path / "variant.toml").write_text('extends = "base.toml"\nname = "variant"\nbatch = 8\n')
    variant = load_config(tmp_path / "variant.toml")
    assert (variant.name, variant.architecture, variant.steps, variant.batch) == ("variant", "pod", 40, 8)
    assert "extends" not in variant.to_dict()
    (tmp_path / "base.toml").write_text('extends = "variant.toml"\nname = "base"\n')
    with pytest.raises(TrainingInputError, match=r"base.toml: extends variant.toml, which leads back here"):
        load_config(tmp_path / "variant.toml")


def test_bad_input_is_refused_naming_the_file_or_key(coarse_data: Path, tmp_path: Path) -> None:
    with pytest.raises(TrainingInputError, match=r"architecture = 'transformer': expected one of"):
        parse_config(tiny_config(architecture="transformer"), "x.toml")
    with pytest.raises(TrainingInputError, match=r"unknown key\(s\) \['learning_rate'\]"):
        parse_config(tiny_config(learning_rate=1.0), "x.toml")
    with pytest.raises(TrainingInputError, match=r"forces = true needs a reduced architecture"):
        parse_config(tiny_config(forces=True), "x.toml")
    with pytest.raises(TrainingInputError, match=r'force_mode = "residual" .* green-linear or green-tangent'):
        parse_config(tiny_config(architecture="pod", forces=True, force_mode="residual"), "x.toml")
    with pytest.raises(TrainingInputError, match=r"force_reads_field = true needs forces = true"):
        parse_config(tiny_config(architecture="pod", force_reads_field=True), "x.toml")
    with pytest.raises(TrainingInputError, match=r"force_reads_grasps = true needs forces = true and encoder"):
        parse_config(tiny_config(architecture="pod", forces=True, force_reads_grasps=True), "x.toml")
    with pytest.raises(TrainingInputError, match=r'interaction_geometry = true needs .* encoder = "grasps"'):
        parse_config(tiny_config(architecture="pod", interaction_geometry=True), "x.toml")
    with pytest.raises(TrainingInputError, match="interaction_depth = true needs interaction_geometry = true"):
        parse_config(tiny_config(architecture="pod", encoder="grasps", interaction_depth=True), "x.toml")
    # The network refuses them too, built from code rather than a configuration.
    with pytest.raises(ValueError, match="force_reads_grasps needs a force head"):
        ReducedNet("pod", 8, 32, "grasps", force_reads_grasps=True)
    with pytest.raises(ValueError, match="a force head reads the grasps of grasp encoders only"):
        ReducedNet("pod", 8, 32, "linear", force_width=16, force_reads_grasps=True)
    with pytest.raises(ValueError, match="surface geometry is an input of grasp encoders only"):
        ReducedNet("pod", 8, 32, "linear", geometry=True)
    with pytest.raises(TrainingInputError, match=r'held_nodes_in_loss = false needs architecture = "pod"'):
        parse_config(tiny_config(architecture="deeponet", held_nodes_in_loss=False), "x.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x"\narchitecture = "pointnet"\nmethod = "res"\nepsilon = "large"\n')
    with pytest.raises(TrainingInputError, match=r"bad.toml: epsilon = 'large'"):
        load_config(bad)

    data = tmp_path / "data"
    shutil.copytree(coarse_data, data)
    dataset = open_dataset(data)
    with pytest.raises(TrainingInputError, match=r"unknown split 'holdout'"):
        dataset.load("holdout")
    chunk = data / "chunk-00001.safetensors"
    chunk.write_bytes(chunk.read_bytes()[:1000])
    with pytest.raises(TrainingInputError, match=r"chunk-00001.safetensors: unreadable chunk"):
        dataset.load("train")
    (data / "chunk-00000.json").unlink()
    (data / "chunk-00001.json").unlink()
    with pytest.raises(TrainingInputError, match=r"no complete samples in split 'train'"):
        dataset.load("train")

    with pytest.raises(TrainingInputError, match=r"train_samples = -2: must be 0 \(all\) or more"):
        parse_config(tiny_config(train_samples=-2), "x.toml")
    with pytest.raises(TrainingInputError, match=r"pod_samples = -1: must be 0 \(all\) or more"):
        parse_config(tiny_config(architecture="pod", pod_samples=-1), "x.toml")
    few = parse_config(tiny_config(architecture="pod", modes=8, pod_samples=4), "x.toml")
    (tmp_path / "few").mkdir()
    with pytest.raises(TrainingInputError, match=r"modes = 8 exceeds the 4 train samples of the POD"):
        ReducedTrainer(few, open_dataset(coarse_data), tmp_path / "few", log=quiet)

    other = tmp_path / "other"
    shutil.copytree(coarse_data, other)
    info = (other / "dataset.json").read_text()
    mesh_hash = open_dataset(coarse_data).mesh.content_hash
    (other / "dataset.json").write_text(info.replace(mesh_hash, "0" * 64))
    with pytest.raises(TrainingInputError, match=r"mesh.safetensors: mesh phantom-liver .* is not the dataset's"):
        open_dataset(other)

    shard = tmp_path / "shard"
    shutil.copytree(coarse_data, shard)
    described = json.loads((shard / "dataset.json").read_text())
    (shard / "dataset.json").write_text(json.dumps({**described, "shard": {"index": 1, "count": 4}}))
    with pytest.raises(TrainingInputError, match=r"holds shard 1/4 of a dataset, not the whole: join"):
        open_dataset(shard)


def test_the_pod_of_a_set_no_wider_than_its_sketch_is_the_svd_of_its_weighted_fields() -> None:
    """11 samples, read in blocks of 3 that do not divide them, against an SVD of the whole weighted
    matrix: the same singular values, and modes orthonormal in L2(Ω) spanning the same subspace."""
    generator = torch.Generator().manual_seed(0)
    fields = torch.randn(11, 5, 3, generator=generator) * torch.linspace(1, 3, 11).reshape(11, 1, 1)
    volumes = torch.rand(5, generator=generator) + 0.5
    basis, singular = weighted_basis(fields, volumes, modes=4, block=3)
    sqrt_v = volumes.double().sqrt().repeat_interleave(3)
    x = fields.reshape(11, -1).double() * sqrt_v
    _, reference, vt = torch.linalg.svd(x, full_matrices=False)
    assert torch.allclose(singular, reference[:4], rtol=1e-10)
    psi = basis.reshape(15, 4) * sqrt_v.unsqueeze(1)
    assert torch.allclose(psi.T @ psi, torch.eye(4, dtype=torch.float64), atol=1e-10)
    assert torch.allclose((vt[:4] @ psi).abs(), torch.eye(4, dtype=torch.float64), atol=1e-8)


def test_the_randomized_pod_finds_the_leading_modes_of_a_set_wider_than_its_sketch() -> None:
    """200 samples of 8 patterns and a little noise, sketched 12 wide: the 4 leading singular values
    and modes of the SVD, to the precision the noise allows."""
    generator = torch.Generator().manual_seed(1)
    patterns = torch.randn(8, 60, generator=generator) * torch.tensor([40, 20, 10, 5, 3, 2, 1.5, 1.0]).unsqueeze(1)
    fields = torch.randn(200, 8, generator=generator) @ patterns + 1e-3 * torch.randn(200, 60, generator=generator)
    volumes = torch.rand(20, generator=generator) + 0.5
    basis, singular = weighted_basis(fields.reshape(200, 20, 3), volumes, modes=4, oversample=8)
    sqrt_v = volumes.double().sqrt().repeat_interleave(3)
    _, reference, vt = torch.linalg.svd(fields.double() * sqrt_v, full_matrices=False)
    assert torch.allclose(singular, reference[:4], rtol=1e-8)
    psi = basis.reshape(60, 4) * sqrt_v.unsqueeze(1)
    assert torch.allclose((vt[:4] @ psi).abs(), torch.eye(4, dtype=torch.float64), atol=1e-6)


def test_the_served_error_in_coefficient_space_leaves_out_the_held_nodes_as_nak_does(coarse_data: Path) -> None:
    """nak answers held nodes with their prescribed displacement: the error a POD network's loss and val
    DCM take from coefficients, less `HeldNodes`' share, is that of Φ g over the mesh with held rows
    overwritten, on real samples."""
    dataset = open_dataset(coarse_data)
    volumes, train, val = dataset.mesh.nodal_volumes, dataset.load("train"), dataset.load("val")
    basis, _ = weighted_basis(train.fields, volumes, 6)
    p = project(val.fields, basis, volumes)
    g = p["g"] + 0.3 * torch.randn(p["g"].shape, generator=torch.Generator().manual_seed(0))
    _, mask, ids = interaction_batch(dataset.mesh, val, geometry=False)
    held = HeldNodes(ids, mask, val.fields, volumes)
    norm = (val.fields.double() ** 2).sum(-1) @ volumes.double()
    errors = ReducedTrainer._coefficient_error(g, p["g"], p["missed"], norm.float(), held.squared_error(basis, g))
    field = torch.einsum("nkm,bm->bnk", basis, g.double())
    for i, sample in enumerate(val.samples):
        field[i, torch.from_numpy(sample.nodes)] = torch.from_numpy(sample.displacements)
    served = ((((field - val.fields.double()) ** 2).sum(-1) @ volumes.double()) / norm).sqrt()
    assert torch.allclose(errors.double(), served, rtol=1e-4), (errors, served)
    whole = ReducedTrainer._coefficient_error(g, p["g"], p["missed"], norm.float())
    assert (whole > errors).all()  # the network's own field misses its held nodes too


def test_an_interrupted_run_resumes_to_the_same_weights(coarse_data: Path, tmp_path: Path) -> None:
    dataset = open_dataset(coarse_data)
    config = parse_config(tiny_config(method="reg"), "tiny")
    straight = tmp_path / "straight"
    straight.mkdir()
    Trainer(config, dataset, straight, log=quiet).run()

    class Interrupt(Exception):
        pass

    def stop_after_first_checkpoint(message: str) -> None:
        if "val DCM" in message:
            raise Interrupt

    resumed = tmp_path / "resumed"
    resumed.mkdir()
    with pytest.raises(Interrupt):
        Trainer(config, dataset, resumed, log=stop_after_first_checkpoint).run()
    messages: list[str] = []
    Trainer(config, dataset, resumed, log=messages.append).run()
    assert any("resumed at step 3" in m for m in messages), messages
    a = torch.load(straight / "checkpoint.pt", weights_only=False)["model"]
    b = torch.load(resumed / "checkpoint.pt", weights_only=False)["model"]
    for key in a:
        assert torch.allclose(a[key], b[key], atol=1e-6), key

    other = parse_config(tiny_config(method="reg", batch=5), "tiny")
    with pytest.raises(TrainingInputError, match=r"checkpoint.pt: was written with another configuration"):
        Trainer(other, dataset, resumed, log=quiet)


def test_an_averaged_run_keeps_and_resumes_the_moving_average_of_its_weights(coarse_data: Path, tmp_path: Path) -> None:
    dataset = open_dataset(coarse_data)

    def train(name: str, val_every: int, log: Any = quiet) -> Path:
        run_dir = tmp_path / name
        run_dir.mkdir(exist_ok=True)
        Trainer(parse_config(tiny_config(ema=0.5, val_every=val_every), "tiny"), dataset, run_dir, log=log).run()
        return run_dir

    # Validated once, at the end: what is kept is the average, not the last weights.
    once = train("once", 6)
    checkpoint = torch.load(once / "checkpoint.pt", weights_only=False)
    kept = torch.load(once / "best.pt", weights_only=True)
    assert kept.keys() == checkpoint["ema"].keys()
    assert all(torch.equal(kept[k], checkpoint["ema"][k]) for k in kept)
    assert any(not torch.equal(checkpoint["ema"][k], checkpoint["model"][k]) for k in kept)

    class Interrupt(Exception):
        pass

    def stop_at_the_first_checkpoint(message: str) -> None:
        if "val DCM" in message:
            raise Interrupt

    straight = train("straight", 3)
    with pytest.raises(Interrupt):
        train("resumed", 3, stop_at_the_first_checkpoint)
    resumed = train("resumed", 3)
    a = torch.load(straight / "checkpoint.pt", weights_only=False)["ema"]
    b = torch.load(resumed / "checkpoint.pt", weights_only=False)["ema"]
    for key in a:
        assert torch.allclose(a[key], b[key], atol=1e-6), key
    with pytest.raises(TrainingInputError, match="ema = 1.0"):
        parse_config(tiny_config(ema=1.0), "tiny")


def test_a_run_is_not_resumed_on_data_of_another_volumetric_law(coarse_data: Path, tmp_path: Path) -> None:
    def relabelled(law: str) -> Path:
        """The coarse set as if solved under `law`: the labels are what training compares."""
        copy = tmp_path / law
        shutil.copytree(coarse_data, copy)
        info = json.loads((copy / "dataset.json").read_text())
        info.update(regime="nonlinear", volumetric_law=law)
        (copy / "dataset.json").write_text(json.dumps(info))
        return copy

    config = parse_config(tiny_config(method="reg", steps=3), "tiny")
    run = tmp_path / "run"
    run.mkdir()
    Trainer(config, open_dataset(relabelled("ln-j-squared")), run, log=quiet).run()
    summary = json.loads((run / "summary.json").read_text())
    assert summary["volumetric_law"] == "ln-j-squared"
    older = open_dataset(relabelled("j-minus-one-squared"))
    with pytest.raises(
        TrainingInputError, match=r"under the volumetric law ln-j-squared; .* under j-minus-one-squared"
    ):
        Trainer(config, older, run, log=quiet)
    with pytest.raises(
        TrainingInputError, match=r"under the volumetric law ln-j-squared; .* under j-minus-one-squared"
    ):
        export(config, older, run, tmp_path / "models", log=quiet)


def test_a_run_is_not_resumed_on_another_set(coarse_data: Path, tmp_path: Path) -> None:
    config = parse_config(tiny_config(method="reg", steps=3), "tiny")
    run = tmp_path / "run"
    run.mkdir()
    dataset = open_dataset(coarse_data)
    Trainer(config, dataset, run, log=quiet).run()
    # The same set resumes; one with other chunks on disk (a set still being made) or another seed does not.
    Trainer(config, dataset, run, log=quiet)
    partial = tmp_path / "partial"
    shutil.copytree(coarse_data, partial)
    (partial / "chunk-00001.json").unlink()
    with pytest.raises(TrainingInputError, match=r"was trained on \d+ train samples of a 100-sample set of seed 3; "):
        Trainer(config, open_dataset(partial), run, log=quiet)
    # Trained on a set still being made, the summary names the chunks it had (the whole set's names none).
    assert "chunks" not in json.loads((run / "summary.json").read_text())
    early = tmp_path / "early"
    early.mkdir()
    Trainer(config, open_dataset(partial), early, log=quiet).run()
    assert json.loads((early / "summary.json").read_text())["chunks"] == [0]
    reseeded = tmp_path / "reseeded"
    shutil.copytree(coarse_data, reseeded)
    info = json.loads((reseeded / "dataset.json").read_text())
    (reseeded / "dataset.json").write_text(json.dumps({**info, "seed": 5}))
    with pytest.raises(TrainingInputError, match=r"of seed 5: a run is not resumed on another set"):
        Trainer(config, open_dataset(reseeded), run, log=quiet)


@pytest.fixture(scope="module")
def more_data(nak_binary: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A second coarse set, of seed 4, that only adds training samples."""
    return coarse_set(nak_binary, tmp_path_factory.mktemp("data") / "more", 12, 8, seed=4, chunk_size=10)


def test_sets_of_other_seeds_add_every_sample_to_the_train_split(
    coarse_data: Path, more_data: Path, tmp_path: Path
) -> None:
    config = parse_config(tiny_config(method="reg", steps=3), "tiny")
    dataset, more = open_dataset(coarse_data), open_dataset(more_data)
    (tmp_path / "alone").mkdir()
    alone = Trainer(config, dataset, tmp_path / "alone", log=quiet)
    run = tmp_path / "run"
    run.mkdir()
    joined = Trainer(config, dataset.joined([more]), run, log=quiet)
    # Every sample of the added set, whatever its split, trains; val stays the first set's alone.
    assert len(joined.train) == len(alone.train) + 20
    assert [s.index for s in joined.val.samples] == [s.index for s in alone.val.samples]
    assert torch.equal(joined.train.fields[-20:], more.load("all").fields)
    joined.run()
    recorded = [{"dataset": str(more_data), "seed": 4, "single": 12, "multi": 8}]
    assert json.loads((run / "summary.json").read_text())["more_data"] == recorded
    export(config, dataset, run, tmp_path / "models", log=quiet)
    manifest = tomllib.loads((tmp_path / "models" / "tiny" / "manifest.toml").read_text())
    assert manifest["provenance"]["more_data"] == recorded
    # Resumed without the added set, or with less of it on disk, the run is refused.
    with pytest.raises(TrainingInputError, match=r"of seed 3 and all of a 20-sample set of seed 4; .* gives \d+ train"):
        Trainer(config, dataset, run, log=quiet)
    partial = tmp_path / "partial"
    shutil.copytree(more_data, partial)
    (partial / "chunk-00001.json").unlink()
    with pytest.raises(TrainingInputError, match=r"a run is not resumed on another set"):
        Trainer(config, dataset.joined([open_dataset(partial)]), run, log=quiet)
    # A set still being made is recorded with the chunks it had.
    early = tmp_path / "early"
    early.mkdir()
    Trainer(config, dataset.joined([open_dataset(partial)]), early, log=quiet).run()
    assert json.loads((early / "summary.json").read_text())["more_data"][0]["chunks"] == [0]


def test_only_sets_of_another_seed_and_the_same_law_add_to_the_train_split(
    coarse_data: Path, more_data: Path, tmp_path: Path
) -> None:
    dataset, more = open_dataset(coarse_data), open_dataset(more_data)
    with pytest.raises(TrainingInputError, match=r"has seed 3, as .*coarse has: the same grasps twice"):
        dataset.joined([dataset])
    with pytest.raises(TrainingInputError, match=r"has seed 4, as .*more has: the same grasps twice"):
        dataset.joined([more, more])
    relabelled = tmp_path / "nonlinear"
    shutil.copytree(more_data, relabelled)
    info = json.loads((relabelled / "dataset.json").read_text())
    (relabelled / "dataset.json").write_text(json.dumps({**info, "regime": "nonlinear"}))
    with pytest.raises(TrainingInputError, match=r"only sets of one mesh, regime and law train together"):
        dataset.joined([open_dataset(relabelled)])
    served_prior = parse_config(tiny_config(method="res", prior="green-linear"), "tiny")
    with pytest.raises(TrainingInputError, match=r"not supported with the green-linear prior"):
        Trainer(served_prior, dataset.joined([more]), tmp_path, log=quiet)


def test_holdout_val_trains_on_all_but_the_val_samples_and_is_never_scored_on_a_set_it_trained_on(
    nak_binary: Path, coarse_data: Path, more_data: Path, tmp_path: Path
) -> None:
    """holdout = "val": the test split and the val samples that selection does not take train too (the
    POD's ceiling is then measured on those val samples), the manifest says so, and scoring the model
    on its own set or on an added one is refused by name."""
    dataset = open_dataset(coarse_data)
    values = tiny_config(architecture="pod", method="base", modes=8, width=32, steps=3)
    runs = {holdout: tmp_path / holdout for holdout in ("val+test", "val")}
    trainers = {}
    for holdout, run in runs.items():
        run.mkdir()
        config = parse_config({**values, "holdout": holdout}, "tiny")
        trainers[holdout] = ReducedTrainer(config, dataset.joined([open_dataset(more_data)]), run, log=quiet)
    plain, held = trainers["val+test"], trainers["val"]
    selected = {s.index for s in held.val.samples}
    assert selected == {s.index for s in plain.val.samples}
    own = {s.index for s in dataset.load("all").samples}
    assert (
        len(held.train)
        == len(own) - len(selected) + 20
        == len(plain.train) + len(dataset.load("test")) + len(dataset.load("val")) - len(selected)
    )
    assert selected.isdisjoint(s.index for s in held.train.samples[: len(own) - len(selected)])
    held.run()
    config = parse_config({**values, "holdout": "val"}, "tiny")
    export(config, dataset, runs["val"], tmp_path / "models", log=quiet)
    model = tmp_path / "models" / "tiny"
    assert tomllib.loads((model / "manifest.toml").read_text())["provenance"]["holdout"] == "val"
    for data, seed in ((coarse_data, 3), (more_data, 4)):
        with pytest.raises(TrainingInputError, match=rf"trained on the samples of seed {seed}, which .* holds"):
            evaluate(model, data, nak_binary, COARSE)
    with pytest.raises(TrainingInputError, match=r'holdout = "val" needs no prior or the Kelvinlet'):
        parse_config(tiny_config(method="res", prior="green-linear", holdout="val"), "tiny")


@pytest.fixture(scope="module")
def exported(coarse_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, Path]]:
    """A trained and an untrained +Res PointNet exported from the coarse dataset: (models root, runs)."""
    dataset = open_dataset(coarse_data)
    runs = tmp_path_factory.mktemp("runs")
    models = tmp_path_factory.mktemp("models")
    for name, steps, lr in [("tiny-trained", 150, 3e-3), ("tiny-untrained", 1, 1e-12)]:
        config = parse_config(tiny_config(name=name, steps=steps, lr=lr, val_every=50, batch=8), "tiny")
        (runs / name).mkdir()
        Trainer(config, dataset, runs / name, log=quiet).run()
        export(config, dataset, runs / name, models, log=quiet)
    yield models, runs


def test_exported_models_are_served_as_onnxruntime_computes_them(
    nak_binary: Path, coarse_data: Path, exported: tuple[Path, Path]
) -> None:
    models, runs = exported
    manifest = tomllib.loads((models / "tiny-trained" / "manifest.toml").read_text())
    assert manifest["model"]["method"] == "res" and manifest["model"]["mode"] == "residual"
    assert manifest["prior"]["epsilon_m"] == 0.02
    assert manifest["provenance"]["dataset_seed"] == 3 and manifest["provenance"]["steps"] == 150
    # The commit the weights were trained at, as the run recorded it, and the export's beside it.
    trained_at = json.loads((runs / "tiny-trained" / "summary.json").read_text())["commit"]
    assert manifest["provenance"]["commit"] == trained_at and manifest["provenance"]["exported_at"]
    assert (models / "tiny-trained" / "config.toml").is_file()
    dataset = open_dataset(coarse_data)
    sample = dataset.load("test").samples[0]
    pb, rpc = client.load_stubs()
    args = ["--mesh", str(COARSE), "--models", str(models)]
    with start_server(nak_binary, args) as address, grpc.insecure_channel(address) as channel:
        stub = rpc.DeformationStub(channel)
        listed = {m.name: dict(m.metadata) for m in stub.ListModels(pb.ListModelsRequest()).models}
        assert listed["tiny-trained"]["prior.epsilon_m"] == "0.02"
        grasps = [
            pb.Grasp(nodes=[node], displacement=pb.Vec3(x=u[0], y=u[1], z=u[2]))
            for node, u in zip(sample.nodes.tolist(), sample.displacements.tolist(), strict=True)
        ]
        request = pb.PredictRequest(model="tiny-trained", grasps=grasps)
        served = np.frombuffer(stub.Predict(request).displacements, dtype="<f4").reshape(-1, 3)

    features = np.zeros((1, dataset.mesh.node_count, 7), dtype=np.float32)
    features[0, :, :3] = dataset.mesh.positions.numpy()
    features[0, sample.nodes, 3:6] = sample.displacements
    features[0, sample.nodes, 6] = 1.0
    session = onnxruntime.InferenceSession(str(models / "tiny-trained" / "model.onnx"))
    (network,) = session.run(["displacement"], {"features": features})
    _, points, u, mask = pad_points(
        dataset.mesh.positions, [torch.from_numpy(sample.nodes)], [torch.from_numpy(sample.displacements)]
    )
    prior = Prior(dataset.mesh.prior[0], 0.02, dataset.mesh.prior[2])
    expected = network[0] + prior.evaluate(dataset.mesh.positions, points, u, mask)[0].numpy()
    expected[sample.nodes] = sample.displacements  # held nodes answer the grasp (docs/design.md §7)
    relative = np.linalg.norm(served - expected) / np.linalg.norm(expected)
    assert relative < 1e-5, f"relative difference {relative:.2e}"


def test_training_beats_the_untrained_network_through_nak_eval(
    nak_binary: Path, coarse_data: Path, exported: tuple[Path, Path]
) -> None:
    models, _ = exported
    trained = evaluate(models / "tiny-trained", coarse_data, nak_binary, COARSE)
    untrained = nak_eval(nak_binary, coarse_data, "tiny-untrained", COARSE, models)["subsets"]["combined"]
    assert trained["dcm_combined"] > untrained["dcm"] + 5.0, (trained, untrained)
    written = tomllib.loads((models / "tiny-trained" / "manifest.toml").read_text())["metrics"]
    assert written["dcm_code_combined"] == trained["dcm_code_combined"]
    assert written["network_ms_p50"] > 0 and written["timed_requests"] > 0


@pytest.fixture(scope="module")
def reduced(coarse_data: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Reduced-basis networks from the coarse dataset: a trained POD +Res in three shipping forms (f32
    and f16 basis files, folded graph), its untrained twin, an ensemble of three, two ensembles of two
    grasp encoders (one trained on the served field's error alone), a POD +Reg grasp encoder reading
    surface geometry (its regularizer's Kelvinlet grasps get it too), and a DeepONet +Reg with the
    pooled encoder."""
    dataset = open_dataset(coarse_data)
    runs = tmp_path_factory.mktemp("reduced-runs", numbered=False)
    models = tmp_path_factory.mktemp("reduced-models")
    pod = dict(architecture="pod", modes=8, width=32, steps=200, batch=8, lr=3e-3, val_every=100)
    variants: list[dict[str, Any]] = [
        dict(name="pod-trained", basis_precision="f32", **pod),
        dict(name="pod-f16", basis_precision="f16", **pod),
        dict(name="pod-graph", form="graph", **pod),
        dict(name="pod-untrained", **{**pod, "steps": 1, "lr": 1e-12}),
        dict(name="pod-ensemble", members=3, basis_precision="f32", **pod),
        dict(name="pod-grasps", encoder="grasps", members=2, basis_precision="f32", **pod),
        dict(name="pod-served-loss", encoder="grasps", members=2, held_nodes_in_loss=False, **pod),
        dict(name="pod-reg-geometry", method="reg", encoder="grasps", interaction_geometry=True, **pod),
        dict(
            name="pod-reg-depth",
            method="reg",
            encoder="grasps",
            interaction_geometry=True,
            interaction_depth=True,
            **pod,
        ),
        dict(
            name="deeponet-reg",
            architecture="deeponet",
            method="reg",
            encoder="pooled",
            modes=8,
            width=32,
            steps=30,
            batch=4,
        ),
    ]
    for values in variants:
        config = parse_config(tiny_config(**values), "tiny")
        run = runs / ("pod-trained" if values["name"] in ("pod-f16", "pod-graph") else values["name"])
        if not (run / "summary.json").is_file():
            run.mkdir(exist_ok=True)
            (ReducedTrainer(config, dataset, run, log=quiet)).run()
        export(config, dataset, run, models, log=quiet)
    return models


def test_reduced_networks_are_served_as_their_graph_and_basis_compute_them(
    nak_binary: Path, coarse_data: Path, reduced: Path
) -> None:
    dataset = open_dataset(coarse_data)
    manifest = tomllib.loads((reduced / "pod-trained" / "manifest.toml").read_text())
    assert manifest["model"]["inputs"] == ["interaction"] and manifest["model"]["mode"] == "residual"
    sample = dataset.load("test").samples[0]
    pb, rpc = client.load_stubs()
    args = ["--mesh", str(COARSE), "--models", str(reduced)]
    with start_server(nak_binary, args) as address, grpc.insecure_channel(address) as channel:
        stub = rpc.DeformationStub(channel)
        grasps = [
            pb.Grasp(nodes=[node], displacement=pb.Vec3(x=u[0], y=u[1], z=u[2]))
            for node, u in zip(sample.nodes.tolist(), sample.displacements.tolist(), strict=True)
        ]
        served = {
            name: np.frombuffer(stub.Predict(pb.PredictRequest(model=name, grasps=grasps)).displacements, "<f4")
            for name in (
                "pod-trained",
                "pod-f16",
                "pod-graph",
                "pod-ensemble",
                "pod-grasps",
                "pod-reg-geometry",
                "pod-reg-depth",
                "deeponet-reg",
            )
        }

    positions = dataset.mesh.positions
    interaction = np.concatenate([positions[sample.nodes].numpy(), sample.displacements], axis=1)[None].astype("f4")
    _, points, u, mask = pad_points(
        positions, [torch.from_numpy(sample.nodes)], [torch.from_numpy(sample.displacements)]
    )
    prior = Prior(dataset.mesh.prior[0], 0.02, dataset.mesh.prior[2])
    prior_field = prior.evaluate(positions, points, u, mask)[0].numpy().reshape(-1)

    nodes = torch.from_numpy(sample.nodes)
    with_geometry, with_depth = (
        interaction_input(
            dataset.mesh, nodes, positions[nodes], torch.from_numpy(sample.displacements), geometry=True, depth=depth
        )[None].numpy()
        for depth in (False, True)
    )
    assert with_depth.shape[-1] == 11 and (with_depth[0, :, -1] > 0).all()  # held nodes lie on the surface

    def expected(name: str, inputs: np.ndarray = interaction, prior: bool = True) -> np.ndarray:
        """The graph's coefficients (onnxruntime) times the basis file, plus the prior for a residual;
        the held nodes answer the grasp (docs/design.md §7)."""
        session = onnxruntime.InferenceSession(str(reduced / name / "model.onnx"))
        (g,) = session.run(["coefficients"], {"interaction": inputs})
        basis = load_file(str(reduced / name / "basis.safetensors"))["basis"]
        field = (basis @ g[0]).reshape(-1, 3) + (prior_field.reshape(-1, 3) if prior else 0.0)
        field[sample.nodes] = sample.displacements
        return np.asarray(field.reshape(-1))

    def relative(a: np.ndarray, b: np.ndarray) -> float:
        return float(np.linalg.norm(a - b) / np.linalg.norm(b))

    assert relative(served["pod-trained"], expected("pod-trained")) < 1e-5
    assert relative(served["pod-graph"], expected("pod-trained")) < 1e-5
    assert 0 < relative(served["pod-f16"], expected("pod-trained")) < 1e-3  # f16 basis: 2⁻¹¹ relative per value
    assert relative(served["pod-ensemble"], expected("pod-ensemble")) < 1e-5
    assert relative(served["pod-grasps"], expected("pod-grasps")) < 1e-5
    assert relative(served["pod-reg-geometry"], expected("pod-reg-geometry", with_geometry, prior=False)) < 1e-5
    # nak computes the organ's depth beneath each held node as training does (src/mesh/depth.rs).
    assert relative(served["pod-reg-depth"], expected("pod-reg-depth", with_depth, prior=False)) < 1e-5
    assert np.isfinite(served["deeponet-reg"]).all()


def test_an_ensemble_answers_the_mean_of_its_members_which_differ(coarse_data: Path, reduced: Path) -> None:
    config = load_config(reduced / "pod-ensemble" / "config.toml")
    run = reduced.parent / "reduced-runs" / "pod-ensemble"
    net, _ = load_reduced(run, config)
    assert isinstance(net.encoder, Ensemble) and len(net.encoder.encoders) == 3
    sample = open_dataset(coarse_data).load("test").samples[0]
    positions = open_dataset(coarse_data).mesh.positions
    interaction = torch.cat([positions[sample.nodes].float(), torch.from_numpy(sample.displacements).float()], 1)[None]
    with torch.no_grad():
        each = [member(interaction) for member in net.encoder.encoders]
        assert torch.allclose(net.encoder(interaction), torch.stack(each).mean(0), atol=1e-6)
    assert float((each[0] - each[1]).norm()) > 1e-3 * float(each[0].norm())  # own weights, own batches
    with pytest.raises(TrainingInputError, match="members > 1"):
        parse_config(tiny_config(members=2), "tiny")  # PointNet: no ensembles


def test_the_grasp_encoder_sees_grasps_whatever_their_order_or_padding(coarse_data: Path, reduced: Path) -> None:
    """Its offsets are in the train split's own unit (the grasps' RMS radius: millimetres on the
    phantom), its answer does not depend on the order of the points or on padding, and a grasp's
    point count changes it where mean and max pooling alone could not tell."""
    config = load_config(reduced / "pod-grasps" / "config.toml")
    net, _ = load_reduced(reduced.parent / "reduced-runs" / "pod-grasps", config)
    assert isinstance(net.encoder, Ensemble)
    member = net.encoder.encoders[0]
    assert isinstance(member, GraspEncoder) and 1e-4 < float(member.r_scale) < 5e-2
    dataset = open_dataset(coarse_data)
    positions = dataset.mesh.positions.float()
    nodes = torch.tensor([0, 1, 2, 3, 4])
    u = torch.tensor([[0.01, 0.0, 0.0]] * 3 + [[0.0, 0.0, -0.01]] * 2)  # two grasps
    interaction = torch.cat([positions[nodes], u], 1)[None]
    with torch.no_grad():
        g = net.encoder(interaction)
        shuffled = net.encoder(interaction[:, torch.tensor([3, 0, 4, 2, 1])])
        padded = net.encoder(
            torch.cat([interaction, torch.zeros(1, 2, 6)], 1), torch.tensor([[True] * 5 + [False] * 2])
        )
        # The first grasp's points again, at its centroid: same positions pooled, one point more.
        centroid = interaction[:, :3].mean(1, keepdim=True)
        grown = net.encoder(torch.cat([interaction, centroid], 1))
    assert torch.allclose(g, shuffled, atol=1e-5) and torch.allclose(g, padded, atol=1e-5)
    assert float((grown - g).norm()) > 1e-4 * float(g.norm())
    # A force head reads each point's grasp size from the features (their log count), not by counting
    # the points that move alike again: the two agree.
    _, features, _ = member.encode(interaction)
    counted = Encoder.grasp_sizes(member, features)
    assert torch.allclose(member.grasp_sizes(features), counted, rtol=1e-6)
    assert counted.flatten().tolist() == [3, 3, 3, 2, 2]


def older_graph(net: ReducedNet, interaction: torch.Tensor, directory: Path) -> Path:
    """`net`'s graph in `directory` as export wrote it before it folded sizes or wrote served forms."""
    directory.mkdir(parents=True, exist_ok=True)
    torch.onnx.export(
        InteractionGraph(net, None, torch.zeros(0, 3), folded=False),
        (interaction,),
        str(directory / "model.onnx"),
        input_names=["interaction"],
        output_names=["coefficients"],
        dynamic_axes={"interaction": {0: "batch", 1: "points"}, "coefficients": {0: "batch"}},
        opset_version=17,
        dynamo=False,
    )
    return directory


def request_of(
    grasps: list[tuple[int, list[float]]], seed: int, geometry: bool = False, depth: bool = False
) -> torch.Tensor:
    """interaction [1, K, 6]: for each (point count, displacement), that many points near the phantom;
    with `geometry`, [1, K, 10]: each with a unit normal and a nodal volume of about 1e-8 m³ too; with
    `depth`, [1, K, 11]: and a depth of a few centimetres beneath it."""
    rng = torch.Generator().manual_seed(seed)

    def point(u: list[float]) -> torch.Tensor:
        row = [torch.tensor([0.05, 0.02, 0.1]) + 0.03 * torch.randn(3, generator=rng), torch.tensor(u)]
        if geometry:
            normal = torch.randn(3, generator=rng)
            row += [normal / normal.norm(), 1e-8 * (1.0 + torch.rand(1, generator=rng))]
        if depth:
            row.append(0.1 * torch.rand(1, generator=rng))
        return torch.cat(row)

    return torch.stack([point(u) for count, u in grasps for _ in range(count)])[None]


@pytest.mark.parametrize(
    "members,force_width,reads_field,geometry,reads_grasps,depth",
    [
        (3, None, False, False, False, False),
        (1, 16, False, False, False, False),
        (2, 16, True, False, False, False),
        (2, 16, False, True, False, False),
        (2, 16, False, True, True, False),
        (1, 16, False, True, True, True),
    ],
)
def test_the_served_form_of_grasp_encoders_answers_as_they_do(
    members: int, force_width: int | None, reads_field: bool, geometry: bool, reads_grasps: bool, depth: bool
) -> None:
    """Per grasp and sharing what members share (grasp_served.py), for one grasp or several, grasps of
    one point, points in any order, the field's coefficients and the forces are the network's, with the
    points' surface geometry (and the organ's depth) as an input or without, and force heads that read
    the grasps' context."""
    torch.manual_seed(members)
    net = ReducedNet("pod", 8, 32, "grasps", force_width, members, reads_field, geometry, reads_grasps, depth)
    statistics = dict(x_mean=torch.tensor([0.05, 0.02, 0.1]), x_std=torch.tensor([0.05, 0.04, 0.06]))
    for member in net.members:
        member.set_statistics(**statistics, u_scale=torch.full((3,), 0.01), g_scale=torch.rand(8) + 0.5)
        if geometry:
            member.set_statistics(v_scale=torch.tensor([1.5e-8]))
        if depth:
            member.set_statistics(d_scale=torch.tensor([0.05]))
    net.eval()
    served = ServedGraspNet(net).eval()
    requests = [
        [(1, [0.0, 0.0, 0.02])],
        [(9, [0.01, -0.02, 0.0])],
        [(7, [0.01, 0.0, 0.0]), (4, [0.0, 0.0, -0.02])],
        [(3, [0.01, 0.0, 0.0]), (1, [0.0, 0.01, 0.0]), (5, [0.0, 0.0, 0.01])],
    ]
    for seed, grasps in enumerate(requests):
        interaction = request_of(grasps, seed, geometry, depth)
        shuffled = interaction[:, torch.randperm(interaction.shape[1])]
        with torch.no_grad():
            expected, expected_forces = net.encode(interaction)
            g, forces = served(interaction)
            g_shuffled, _ = served(shuffled)
        assert float((g - expected).norm()) <= 1e-5 * float(expected.norm()), grasps
        assert float((g_shuffled - expected).norm()) <= 1e-5 * float(expected.norm()), grasps
        if force_width is None:
            assert forces is None and expected_forces is None
        else:
            assert forces is not None and expected_forces is not None
            assert float((forces - expected_forces).norm()) <= 1e-5 * float(expected_forces.norm()), grasps
    if members > 1:
        net.members[1].set_statistics(r_scale=torch.tensor([2.0]))
        with pytest.raises(ValueError, match="r_scale differ"):
            ServedGraspNet(net)


def test_a_shipped_graph_is_rewritten_in_its_served_form_from_its_own_weights(
    coarse_data: Path, reduced: Path, tmp_path: Path
) -> None:
    """Run directories are not committed: `serve-form` reads the network back from an older graph's
    weights, and writes the served form only where both answer as the graph did."""
    config = load_config(reduced / "pod-grasps" / "config.toml")
    net, _ = load_reduced(reduced.parent / "reduced-runs" / "pod-grasps", config)
    assert batch_is_fixed(onnx.load(str(reduced / "pod-grasps" / "model.onnx")))  # export writes the served form
    positions = open_dataset(coarse_data).mesh.positions
    interaction = torch.cat([positions[:7].float(), torch.tensor([[0.01, 0.0, 0.0]] * 4 + [[0.0, 0.0, -0.01]] * 3)], 1)
    shipped = older_graph(net, interaction[None], tmp_path / "shipped")
    for name in ("config.toml", "manifest.toml"):
        shutil.copy(reduced / "pod-grasps" / name, shipped / name)
    before = len(onnx.load(str(shipped / "model.onnx")).graph.node)

    said = reform(shipped)
    assert "served form" in said and "answers as before" in said, said
    rewritten = onnx.load(str(shipped / "model.onnx"))
    assert batch_is_fixed(rewritten) and len(rewritten.graph.node) < before
    assert tomllib.loads((shipped / "manifest.toml").read_text())["provenance"]["served_form_at"]
    with torch.no_grad():
        expected = net.encoder(interaction[None]).numpy()
    session = onnxruntime.InferenceSession(str(shipped / "model.onnx"))
    (got,) = session.run(None, {"interaction": interaction[None].numpy()})
    assert np.abs(got - expected).max() <= 1e-5 * np.abs(expected).max()
    assert "already in the served form" in reform(shipped)

    # A configuration that is not the graph's network is refused, naming the weight that does not fit.
    other = older_graph(net, interaction[None], tmp_path / "other")
    (other / "config.toml").write_text(
        (shipped / "config.toml").read_text().replace("width = 32", "width = 16"), encoding="utf-8"
    )
    with pytest.raises(TrainingInputError, match=r"is \[32, 10\] in the graph, \[16, 10\] in its configuration"):
        reform(other)
    pooled = tmp_path / "pooled"
    shutil.copytree(reduced / "deeponet-reg", pooled)
    with pytest.raises(TrainingInputError, match="only POD networks of grasp encoders"):
        reform(pooled)


def test_exported_graphs_read_no_fixed_size_at_run_time_and_older_ones_are_folded_alike(
    coarse_data: Path, reduced: Path, tmp_path: Path
) -> None:
    """PyTorch traces `shape[i]` as Shape → Gather even of a fixed axis, and ONNX Runtime then slices
    weights at every request; export folds them, and `fold` does it to a graph exported before."""
    config = load_config(reduced / "pod-grasps" / "config.toml")
    net, _ = load_reduced(reduced.parent / "reduced-runs" / "pod-grasps", config)
    assert fold_static_sizes(onnx.load(str(reduced / "pod-grasps" / "model.onnx"))) == 0

    older = tmp_path / "older"
    positions = open_dataset(coarse_data).mesh.positions
    interaction = torch.cat([positions[:5].float(), torch.full((5, 3), 0.01)], 1)[None]
    older_graph(net, interaction, older)
    assert fold_static_sizes(onnx.load(str(older / "model.onnx"))) > 0  # what export did before
    assert "answers unchanged" in refold_interaction_graph(older)
    assert fold_static_sizes(onnx.load(str(older / "model.onnx"))) == 0
    with torch.no_grad():
        expected = net.encoder(interaction).numpy()
    (got,) = onnxruntime.InferenceSession(str(older / "model.onnx")).run(None, {"interaction": interaction.numpy()})
    assert np.abs(got - expected).max() <= 1e-5 * np.abs(expected).max()

    features = tmp_path / "features"
    features.mkdir()
    shutil.copy(ROOT / "models" / "phantom-liver" / "pointnet-base" / "model.onnx", features / "model.onnx")
    with pytest.raises(TrainingInputError, match="not an interaction-form graph"):
        refold_interaction_graph(features)


def test_reduced_training_beats_the_untrained_network_through_nak_eval(
    nak_binary: Path, coarse_data: Path, reduced: Path
) -> None:
    untrained = nak_eval(nak_binary, coarse_data, "pod-untrained", COARSE, reduced)["subsets"]["combined"]
    # The second trained on the served field's error alone (held nodes left to nak).
    for name in ("pod-trained", "pod-served-loss"):
        trained = evaluate(reduced / name, coarse_data, nak_binary, COARSE)
        assert trained["dcm_combined"] > untrained["dcm"] + 5.0, (name, trained, untrained)
        assert trained["held_nodes"] == "prescribed"


@pytest.mark.parametrize("prior", ["green-linear", "green-tangent"])
def test_a_network_on_a_green_prior_is_trained_and_served_on_it(
    nak_binary: Path, coarse_data: Path, tmp_path: Path, prior: str
) -> None:
    """+Res against green-linear or green-tangent: training reads the prior from `nak dataset fields`,
    the manifest names it, and nak serves the prior + Φ g (building its Green's functions because the
    model needs them)."""
    dataset = open_dataset(coarse_data)
    values = dict(name="pod-green", architecture="pod", prior=prior, modes=8, width=32, steps=60, batch=8)
    config = parse_config(tiny_config(**values), "tiny")
    run = tmp_path / "run"
    run.mkdir()
    ReducedTrainer(config, dataset, run, log=quiet, nak=Nak(nak_binary, COARSE)).run()
    assert (run / f"{prior}-train.safetensors").is_file()
    models = tmp_path / "models"
    export(config, dataset, run, models, log=quiet)
    manifest = tomllib.loads((models / "pod-green" / "manifest.toml").read_text())
    assert manifest["prior"]["model"] == prior

    def served(model: str) -> np.ndarray:
        out = tmp_path / f"{model}.safetensors"
        args = ["dataset", "fields", "--data", str(coarse_data), "--model", model, "--split", "test"]
        Nak(nak_binary, COARSE).run(*args, "--out", str(out), "--models", str(models), f"--{prior}")
        return load_file(str(out))["displacement"]

    network, green = served("pod-green"), served(prior)
    sample = dataset.load("test").samples[0]
    interaction = np.concatenate([dataset.mesh.positions[sample.nodes].numpy(), sample.displacements], axis=1)
    session = onnxruntime.InferenceSession(str(models / "pod-green" / "model.onnx"))
    (g,) = session.run(["coefficients"], {"interaction": interaction[None].astype("f4")})
    basis = load_file(str(models / "pod-green" / "basis.safetensors"))["basis"].astype("f4")
    expected = green[0] + (basis @ g[0]).reshape(-1, 3)
    expected[sample.nodes] = sample.displacements  # held nodes answer the grasp (docs/design.md §7)
    scale = float(np.abs(green[0]).max())
    assert np.abs(network[0] - expected).max() <= 1e-3 * scale


@pytest.mark.parametrize(
    ("prior", "encoder", "ensemble", "geometry"),
    [
        ("kelvinlet", "linear", False, False),
        ("green-linear", "linear", False, False),
        ("kelvinlet", "grasps", False, False),
        ("kelvinlet", "grasps", True, False),
        ("kelvinlet", "grasps", False, True),
    ],
)
def test_a_force_head_is_trained_exported_and_served_as_the_sum_of_its_point_forces(
    nak_binary: Path, coarse_data: Path, tmp_path: Path, prior: str, encoder: str, ensemble: bool, geometry: bool
) -> None:
    """forces = true: the graph gains `forces` [B, K, 3], checked against onnxruntime at export; the
    manifest says how nak serves them (direct on the Kelvinlet; on green-linear, residual: added to its
    exact forces); nak serves each grasp's sum; training lowers the error nak eval measures. The grasp
    encoder gives the head its grasp's size and shape too. An ensemble (whose heads here also read the
    field's coefficients) serves the mean of its members' heads. With `interaction_geometry` the graph
    reads [B, K, 10], and nak feeds it the normals and nodal volumes training saw (the dataset's mesh)."""
    dataset = open_dataset(coarse_data)
    nak = Nak(nak_binary, COARSE)
    models = tmp_path / "models"
    errors = {}
    for name, steps, lr in (("trained", 300, 3e-3), ("untrained", 1, 1e-12)):
        values = dict(name=name, architecture="pod", prior=prior, encoder=encoder, modes=8, width=32)
        values.update(steps=steps, batch=8, lr=lr)
        if ensemble:
            values.update(members=3, force_reads_field=True)
        values.update(interaction_geometry=geometry)
        mode = "direct" if prior == "kelvinlet" else "residual"
        config = parse_config(
            tiny_config(**values, forces=True, force_mode=mode, force_weight=1.0, val_every=100), "tiny"
        )
        run = tmp_path / name
        run.mkdir()
        ReducedTrainer(config, dataset, run, log=quiet, nak=nak).run()
        export(config, dataset, run, models, log=quiet)
    green_args = ["--models", str(models)] + ([f"--{prior}"] if prior != "kelvinlet" else [])
    for name in ("trained", "untrained"):
        manifest = tomllib.loads((models / name / "manifest.toml").read_text())
        assert manifest["forces"]["mode"] == ("direct" if prior == "kelvinlet" else "residual")
        out = tmp_path / f"{name}-eval.json"
        args = ["eval", "--data", str(coarse_data), "--model", name, "--split", "test", "--output", str(out)]
        nak.run(*args, *green_args)
        report = json.loads(out.read_text())
        errors[name] = report["grasp_forces"]["combined"]["mean_relative_error"]
    if prior == "kelvinlet":
        assert errors["trained"] < 0.5 * errors["untrained"], errors
    else:
        # On linear data green-linear's forces are the truth: the head learns to add nothing, and
        # what is served is the prior's forces plus that nothing.
        assert max(errors.values()) < 1e-4, errors

    # Served forces: per grasp, the sum over its points of the graph's output (plus the prior's own).
    sample = next(s for s in dataset.load("test").samples if s.forces is not None and len(s.forces) == 2)
    mesh, nodes = dataset.mesh, sample.nodes
    columns = [mesh.positions[nodes].numpy(), sample.displacements]
    if geometry:
        columns += [mesh.normals[nodes].numpy(), mesh.nodal_volumes[nodes].numpy()[:, None]]
    interaction = np.concatenate(columns, axis=1)
    session = onnxruntime.InferenceSession(str(models / "trained" / "model.onnx"))
    assert session.get_inputs()[0].shape[-1] == (10 if geometry else 6)
    assert [o.name for o in session.get_outputs()] == ["coefficients", "forces"]
    (point_forces,) = session.run(["forces"], {"interaction": interaction[None].astype("f4")})
    learned = np.stack([point_forces[0][sample.grasp_of_point == g].sum(0) for g in range(2)])
    fields = tmp_path / "fields.safetensors"
    args = ["dataset", "fields", "--data", str(coarse_data), "--model", "trained", "--split", "test"]
    nak.run(*args, "--out", str(fields), *green_args)
    row = list(load_file(str(fields))["index"]).index(sample.index)
    served = load_file(str(fields))["grasp_forces"][row]
    expected = learned
    if prior != "kelvinlet":
        out = tmp_path / "prior.safetensors"
        nak.run(
            "dataset",
            "fields",
            "--data",
            str(coarse_data),
            "--model",
            prior,
            "--split",
            "test",
            "--out",
            str(out),
            *green_args,
        )
        expected = expected + load_file(str(out))["grasp_forces"][row]
    assert np.abs(served - expected).max() <= 1e-4 * np.abs(expected).max(), (served, expected)
    if ensemble:
        config = load_config(models / "trained" / "config.toml")
        net, _ = load_reduced(tmp_path / "trained", config)
        assert len(net.force_heads) == 3
        with torch.no_grad():
            points = torch.from_numpy(interaction[None]).float()
            each = [net.encode_member(i, points)[1] for i in range(3)]
            mean = torch.stack([f for f in each if f is not None]).mean(0)[0].numpy()
        assert np.abs(mean - point_forces[0]).max() <= 1e-4 * np.abs(point_forces).max()
    if prior != "kelvinlet" or encoder != "linear":
        return
    # The force report: the prior and the network per subset, the figure, and the head's cost.
    report = write_force_report(
        coarse_data, [models / "trained"], nak_binary, COARSE, tmp_path / "forces", tmp_path, "green-linear"
    )
    text = report.read_text()
    assert "| `green-linear` | single |" in text and "| `trained` | combined |" in text, text
    assert "| `trained` |" in text.split("What the force head costs")[1], text
    assert "| `trained` | single |" in text.split("Where the heads miss")[1], text
    assert (tmp_path / "forces" / "served-against-fem.png").stat().st_size > 10_000
    # The head is timed against its network exported without it, from its run: another run is refused.
    (tmp_path / "mixed").mkdir()
    (tmp_path / "mixed" / "trained").symlink_to(tmp_path / "untrained", target_is_directory=True)
    example = interaction_input(
        dataset.mesh, torch.tensor([0, 1]), dataset.mesh.positions[:2], torch.ones(2, 3) * 0.01, False
    )
    with pytest.raises(TrainingInputError, match="not the run it came from"):
        field_only(models / "trained", tmp_path / "mixed", dataset.mesh, example[None].numpy(), tmp_path / "f.onnx")


def test_grasp_force_misses_are_grouped_by_the_push_against_the_held_nodes_normal() -> None:
    # Node 0's outward normal is +z, node 1's +x; node 2 is held by both grasps and counts for the first.
    normals = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    sample = Sample(
        index=7,
        subset="multi",
        split="test",
        nodes=np.array([0, 2, 1]),
        displacements=np.array([[0.0, 0.0, -0.01], [0.0, 0.0, -0.01], [0.01, 0.0, 0.01]]),
        grasp_of_point=np.array([0, 0, 1]),
        forces=np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 0.0]]),
    )
    cosines = push_cosines(sample, normals, 2)
    assert np.allclose(cosines, [-1 / np.sqrt(2), 1 / np.sqrt(2)])  # normals summed over the held nodes
    assert np.isnan(push_cosines(sample, normals, 3)[2])  # a grasp that shows no node of its own
    assert sample.forces is not None
    served = {"net": {7: sample.forces * np.array([[1.0], [1.5]])}}  # 0 % pushing in, 50 % pulling out
    table = by_direction([sample], normals, {7: sample.forces}, served)
    assert "| `net` | multi | 0.0 % (1) | – | – | 50.0 % (1) |" in table, table
    assert "| `net` | single | – | – | – | – |" in table, table


def test_the_mesh_gnn_carries_its_edges_and_is_served_as_onnxruntime_computes_it(
    nak_binary: Path, coarse_data: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    dataset = open_dataset(coarse_data)
    mesh = dataset.mesh
    model = build("gnn", "cpu", mesh).eval()
    assert isinstance(model, MeshGNN)
    h = torch.randn(2, mesh.node_count, 32)
    trained_path = model.neighbour_mean(h)
    monkeypatch.setattr(torch.onnx, "is_in_onnx_export", lambda: True)
    exported_path = model.neighbour_mean(h)
    monkeypatch.undo()
    assert torch.allclose(trained_path, exported_path, atol=1e-5)
    # A node's mean is over its tetrahedral neighbours: check one by hand.
    edges = mesh.edges()
    node = int(edges[0, 0])
    neighbours = torch.cat([edges[1, edges[0] == node], edges[0, edges[1] == node]])
    assert torch.allclose(trained_path[:, node], h[:, neighbours].mean(1), atol=1e-5)

    config = parse_config(tiny_config(name="gnn-tiny", architecture="gnn", steps=20, batch=4), "tiny")
    run = tmp_path / "run"
    run.mkdir()
    Trainer(config, dataset, run, log=quiet).run()
    models = tmp_path / "models"
    export(config, dataset, run, models, log=quiet)  # checks onnxruntime against PyTorch
    out = tmp_path / "fields.safetensors"
    args = ["dataset", "fields", "--data", str(coarse_data), "--model", "gnn-tiny", "--split", "test"]
    Nak(nak_binary, COARSE).run(*args, "--out", str(out), "--models", str(models))
    served = load_file(str(out))["displacement"][0]
    sample = dataset.load("test").samples[0]
    features = np.zeros((1, mesh.node_count, 7), dtype=np.float32)
    features[0, :, :3] = mesh.positions.numpy()
    features[0, sample.nodes, 3:6] = sample.displacements
    features[0, sample.nodes, 6] = 1.0
    session = onnxruntime.InferenceSession(str(models / "gnn-tiny" / "model.onnx"))
    (network,) = session.run(["displacement"], {"features": features})
    _, points, u, mask = pad_points(
        mesh.positions, [torch.from_numpy(sample.nodes)], [torch.from_numpy(sample.displacements)]
    )
    expected = (
        network[0] + Prior(mesh.prior[0], 0.02, mesh.prior[2]).evaluate(mesh.positions, points, u, mask)[0].numpy()
    )
    expected[sample.nodes] = sample.displacements  # held nodes answer the grasp (docs/design.md §7)
    assert np.linalg.norm(served - expected) / np.linalg.norm(expected) < 1e-5


def test_a_learning_curve_point_trains_on_samples_spread_over_both_subsets(coarse_data: Path, tmp_path: Path) -> None:
    config = parse_config(tiny_config(train_samples=12), "tiny")
    trainer = Trainer(config, open_dataset(coarse_data), tmp_path, log=quiet)
    assert len(trainer.train) == 12
    assert {s.subset for s in trainer.train.samples} == {"single", "multi"}


BOX = ROOT / "tests" / "fixtures" / "box.msh"


def test_load_path_states_train_as_samples_of_their_share_of_the_grasp(nak_binary: Path, tmp_path: Path) -> None:
    data = tmp_path / "data"
    args = ["datagen", "--mesh", str(BOX), "--regime", "nonlinear", "--single", "12", "--multi", "0", "--seed", "0"]
    args += ["--chunk-size", "6", "--cache-dir", str(tmp_path / "cache"), "--out", str(data)]
    subprocess.run([str(nak_binary), *args], check=True, capture_output=True)
    dataset = open_dataset(data)
    train = dataset.load("train")
    states = dataset.load_path_states(train.samples, dataset.complete_chunks(), 0.3)
    assert states is not None and len(states) >= len(train)
    by_index = {s.index: (s, train.fields[i]) for i, s in enumerate(train.samples)}
    for state, field in zip(states.samples, states.fields):
        sample, whole = by_index[state.index]
        # The grasped nodes sit where that share of the grasp puts them; the rest moves less than at
        # the whole grasp, and not in proportion (the organ is nonlinear).
        share = float(np.linalg.norm(state.displacements) / np.linalg.norm(sample.displacements))
        assert 0.3 <= share < 1.0 and state.forces is None
        assert np.allclose(state.displacements, share * sample.displacements)
        assert torch.allclose(field[sample.nodes], torch.from_numpy(state.displacements).float(), atol=1e-6)
        assert 0 < float(field.norm()) < float(whole.norm())
    # Only the samples asked for, and only the states at the share asked for or more.
    assert dataset.load_path_states(train.samples[:1], dataset.complete_chunks(), 0.3) is not None
    assert dataset.load_path_states(train.samples, dataset.complete_chunks(), 0.999) is None
    config = parse_config(
        tiny_config(architecture="pod", method="base", modes=2, width=16, steps=4, val_every=2, path_states_from=0.3),
        "tiny",
    )
    run = tmp_path / "run"
    run.mkdir()
    trainer = ReducedTrainer(config, dataset, run, log=quiet)
    assert len(trainer.train) == len(train) + len(states) and trainer.path_states == len(states)
    trainer.run()
    summary = json.loads((run / "summary.json").read_text())
    assert (summary["train_samples"], summary["path_states"]) == (len(train), len(states))
    export(config, dataset, run, tmp_path / "models", log=quiet)
    manifest = tomllib.loads((tmp_path / "models" / "tiny" / "manifest.toml").read_text())
    assert manifest["provenance"]["path_states"] == len(states)
    for bad, words in (
        (dict(path_states_from=1.5), r"must be in \[0, 1\]"),
        (dict(path_states_from=0.5, forces=True), "a network without forces"),
        (dict(path_states_from=0.5, method="res", prior="green-linear"), "a network without forces"),
    ):
        with pytest.raises(TrainingInputError, match=words):
            parse_config(tiny_config(architecture="pod", **bad), "tiny")
