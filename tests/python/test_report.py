"""The report's figure: names of points close together are placed where they do not overlap."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.text import Annotation  # noqa: E402
from nak_training.report import place_labels  # noqa: E402


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
