"""The report's figure: names of points close together are placed where they do not overlap."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.text import Annotation  # noqa: E402
from nak_training.report import Entry, learning_curve, place_labels, recipe, table  # noqa: E402


def test_names_of_neighbouring_points_do_not_overlap() -> None:
    fig, ax = plt.subplots(figsize=(7.5, 5))
    names = [("pod-res-fast", 0.13, 91.0), ("pod-base", 0.14, 89.6), ("pod-reg", 0.16, 86.3), ("far", 20.0, 60.0)]
    ax.scatter([x for _, x, _ in names], [y for *_, y in names])
    ax.set_xscale("log")
    fig.tight_layout()
    place_labels(ax, names)
    fig.canvas.draw()
    boxes = {t.get_text(): t.get_window_extent() for t in ax.texts}
    assert set(boxes) == {name for name, _, _ in names}
    points = {name: (x, y) for name, x, y in names}
    for text in ax.texts:
        assert isinstance(text, Annotation) and tuple(text.xy) == points[text.get_text()]
    listed = list(boxes.values())
    for i, a in enumerate(listed):
        for b in listed[i + 1 :]:
            assert not a.overlaps(b), (a, b)
    plt.close(fig)


def test_the_nonlinear_table_sets_nak_beside_the_papers_table_3() -> None:
    entry = Entry("pointnet-res-nl", "pointnet", "res", "all", 0.015, {"dcm_code_combined": 71.234}, "nonlinear")
    linear_twin = Entry("pointnet-res", "pointnet", "res", "all", 0.015, {"dcm_code_combined": 78.12})
    baselines = {"green-linear — nonlinear": {"dcm_code_single": 33.0, "dcm_code_combined": 35.7}}
    lines = table([entry, linear_twin], "dcm_code", baselines, with_paper=True, regime="nonlinear")
    ours = next(line for line in lines if line.startswith("| PointNet (nak"))
    cells = [c.strip() for c in ours.strip("|").split("|")]
    # Multi +Res is the 8th figure (Indiv. and Comb. Base/+Res/+Reg first); the linear twin is not read.
    assert cells[8] == "71.23" and cells.count("–") == 8
    paper = next(line for line in lines if line.startswith("| PointNet (paper"))
    assert "85.05" in paper and "84.75" in paper and "96.54" not in paper
    assert any("58.88" in line for line in lines if line.startswith("| Kelvinlet (paper)"))
    assert any(line.startswith("| green-linear — nonlinear | 33.00") for line in lines)


def test_the_learning_curve_orders_a_configurations_sizes_and_skips_other_models(tmp_path: Path) -> None:
    def entry(name: str, samples: int, dcm: float, recipe: str = "res", scored_as_served: bool = True) -> Entry:
        metrics: dict[str, Any] = {"dcm_combined": dcm}
        if scored_as_served:
            metrics["held_nodes"] = "prescribed"
        return Entry(name, "pod", "res", "all", 0.01, metrics, "nonlinear", train_samples=samples, recipe=recipe)

    entries = [
        entry("pod-res-nl-n800", 800, 70.0),
        entry("pod-res-nl", 1577, 75.5),
        # Scored before held nodes answered the request: marked.
        entry("pod-res-nl-n200", 200, 60.25, scored_as_served=False),
        # Trained alike on more data under another name: the curve's next point, named.
        entry("pod-res-more-nl", 3000, 78.0),
    ]
    entries.append(entry("pod-base-nl", 1577, 71.0, recipe="base"))
    lines = learning_curve(entries, tmp_path / "curve.png")
    assert lines[2:] == [
        "| `pod-res-nl` | 200 → 60.25\\*, 800 → 70.00, 1,577 → 75.50, 3,000 → 78.00 (`pod-res-more-nl`) |"
    ]
    assert (tmp_path / "curve.png").is_file()
    assert learning_curve([entry("pod-base-nl", 1577, 71.0)], tmp_path / "none.png") == []


def test_a_recipe_is_how_a_model_trains_not_on_what_or_how_many_threads(tmp_path: Path) -> None:
    def config(name: str, body: str) -> Path:
        path = tmp_path / f"{name}.toml"
        path.write_text(f'name = "{name}"\narchitecture = "pod"\nmethod = "base"\nlr = 2e-3\n{body}')
        return path

    plain = recipe(config("pod-base-nl", ""))
    assert recipe(config("pod-base-more-nl", 'holdout = "val"\nthreads = 1\ntrain_samples = 0\n')) == plain
    assert recipe(config("pod-base-nl-n1600", "train_samples = 1600\n")) == plain
    assert recipe(config("pod-base-lr-nl", "weight_decay = 1e-3\n")) != plain
    # A key written at its default (as exports write every key) is the same recipe as one left out.
    assert recipe(config("pod-base-full-nl", "held_nodes_in_loss = true\n")) == plain
    assert recipe(config("pod-base-served-nl", "held_nodes_in_loss = false\n")) != plain
    assert recipe(tmp_path / "missing.toml") == ""


def test_res_on_each_green_prior_gets_a_row_of_its_own() -> None:
    def entry(name: str, dcm: float) -> Entry:
        return Entry(name, "pod", "res", "all", 0.01, {"dcm_combined": dcm}, "nonlinear")

    entries = [entry("pod-res-nl", 74.69), entry("pod-res-gl-nl", 76.76), entry("pod-res-gt-nl", 77.5)]
    lines = table(entries, "dcm", {}, with_paper=False, regime="nonlinear")
    rows = {line.split("|")[1].strip(): line for line in lines[2:]}
    assert "76.76" in rows["POD basis + set encoder, +Res on green-linear (nak)"]
    assert "77.50" in rows["POD basis + set encoder, +Res on green-tangent (nak)"]
