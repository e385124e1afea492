"""The report's figures are read by people: no text over another, every bar and its value
inside its panel, plain tick labels."""

import json

import matplotlib
import pytest
from matplotlib.patches import Rectangle
from matplotlib.text import Text

from retrain.demo_report import curves_figure, signed
from retrain.report import per_class_ap_figure
from serving.manifest import GateFigures

matplotlib.use("Agg")


def drawn_texts(figure) -> list[tuple[str, object]]:
    """(text, window extent) of every non-empty text the renderer draws (tick labels of ticks
    outside an axis's view are not drawn)."""
    figure.canvas.draw()
    renderer = figure.canvas.get_renderer()
    hidden = set()
    for axes in figure.axes:
        for axis, (low, high) in ((axes.xaxis, axes.get_xlim()), (axes.yaxis, axes.get_ylim())):
            low, high = min(low, high), max(low, high)
            for tick in axis.get_major_ticks() + axis.get_minor_ticks():
                if not low <= tick.get_loc() <= high:
                    hidden |= {id(tick.label1), id(tick.label2)}
    texts = []
    for text in figure.findobj(Text):
        if id(text) in hidden or not text.get_visible() or not text.get_text().strip():
            continue
        texts.append((text.get_text(), text.get_window_extent(renderer)))
    return texts


def assert_readable(figure) -> None:
    texts = drawn_texts(figure)
    frame = figure.bbox
    for label, box in texts:
        assert frame.x0 <= box.x0 and box.x1 <= frame.x1 + 0.5, f"{label!r} leaves the figure"
        assert frame.y0 <= box.y0 and box.y1 <= frame.y1 + 0.5, f"{label!r} leaves the figure"
    clashes = [
        (a, b)
        for i, (a, box_a) in enumerate(texts)
        for b, box_b in texts[i + 1 :]
        if box_a.overlaps(box_b)
    ]
    assert clashes == []


def figures(ap_2d_car: float) -> tuple[GateFigures, GateFigures]:
    def ap(car, ped, cyc):
        return {"Car": car, "Pedestrian": ped, "Cyclist": cyc, "mAP": (car + ped + cyc) / 3}

    parent = GateFigures(ap(ap_2d_car, 40.0, 30.0), ap(20.0, 5.0, 0.0), ap(25.0, 8.0, 1.0))
    candidate = GateFigures(ap(ap_2d_car - 3, 44.0, 31.0), ap(22.0, 0.0, 2.0), ap(26, 9, 0))
    return parent, candidate


@pytest.mark.parametrize("ap_2d_car", [97.0, 35.0])
def test_per_class_ap_shows_every_bar_and_value_in_its_panel(ap_2d_car):
    # The 2D panel's Car bar is the tallest: with a limit per panel on a shared axis the last
    # panel's (lower) limit used to cut it off and hide its value.
    parent, candidate = figures(ap_2d_car)
    figure = per_class_ap_figure(parent, candidate, "parent 000001", "candidate 000002")
    assert_readable(figure)
    renderer = figure.canvas.get_renderer()
    for axis in figure.axes:
        bottom, top = axis.get_ylim()
        bars = [p for p in axis.patches if isinstance(p, Rectangle)]
        assert len(bars) == 8
        assert all(bar.get_height() <= top for bar in bars)
        panel = axis.get_window_extent(renderer)
        values = [t for t in axis.texts if t.get_text().strip()]
        assert len(values) == 8  # bar_label: one value per bar
        for value in values:
            box = value.get_window_extent(renderer)
            assert panel.y0 <= box.y0 and box.y1 <= panel.y1, value.get_text()


@pytest.mark.parametrize("low, high", [(3.1, 4.6), (0.4, 60.0)])
def test_loss_curves_have_plain_tick_labels_and_whole_steps(tmp_path, low, high):
    run = tmp_path / "run"
    run.mkdir()
    steps = range(0, 7)
    records = [
        {"step": s, "loss_2d": high - (high - low) * s / 6, "loss_3d": (low + high) / 2}
        for s in steps
    ]
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    figure = curves_figure({"labeled-only": run, "detmatch": run})
    assert_readable(figure)
    for axis in figure.axes:
        labels = [t.get_text() for t in axis.get_yticklabels() + axis.get_xticklabels()]
        assert not [t for t in labels if "$" in t or "times" in t or "10^" in t], labels
        xs = [t.get_position()[0] for t in axis.get_xticklabels() if t.get_text()]
        assert all(float(x).is_integer() for x in xs)


def test_a_gain_that_rounds_to_zero_has_no_sign():
    assert signed(-0.04) == "0.0"
    assert signed(0.04) == "0.0"
    assert signed(-0.06) == "-0.1"
    assert signed(2.25) == "+2.2" or signed(2.25) == "+2.3"
