"""The PNG figures of the products: units, colour bars, arrow scales, titles, legends."""

from __future__ import annotations

import numpy as np
import pytest

from plenopiv.products import figures as plots
from plenopiv.products.vectors import VectorResult


@pytest.fixture
def captured(monkeypatch):
    """The figures the plot functions would save (their texts stay inspectable)."""
    figures = []

    def keep(plt, fig, path):
        figures.append(fig)
        return path

    monkeypatch.setattr(plots, "_save", keep)
    yield figures
    import matplotlib.pyplot as plt

    for f in figures:
        plt.close(f)


def _vectors(dt):
    x, y, z = (np.linspace(-1e-3, 1e-3, n) for n in (6, 5, 4))
    shape = (4, 5, 6)
    u = np.full(shape, 2.5e-4)                    # 0.25 mm, 0.25 m/s over 1 ms
    v = np.full(shape, -1.0e-4)
    w = np.linspace(-1e-4, 1e-4, 4)[:, None, None] * np.ones(shape)
    valid = np.ones(shape, bool)
    valid[1, 2, 3] = False
    return VectorResult(x, y, z, u, v, w, valid, np.full(shape, 3.0), dt=dt)


def _texts(fig):
    out = [fig._suptitle.get_text() if fig._suptitle else ""]
    for ax in fig.axes:
        out += [ax.get_ylabel(), ax.get_xlabel(), ax.get_title(loc="left"), ax.get_title()]
        out += [t.get_text() for t in ax.texts]
        for artist in ax.get_children():
            text = getattr(artist, "text", None)
            if hasattr(text, "get_text"):
                out.append(text.get_text())    # quiver keys
    return " | ".join(out)


def test_vector_png_in_m_per_s_with_dt(captured):
    plots.vector_slices(_vectors(1e-3), "unused.png", title="pair run_7")
    fig = captured[0]
    text = _texts(fig)
    assert "pair run_7" in text and "m/s" in text and "mm)" not in text.replace("(mm)", "")
    colorbars = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert len(colorbars) == 2 and all("m/s" in ax.get_ylabel() for ax in colorbars)
    # w spans +-0.1 m/s: the colour scale is in m/s, not in metres
    lo, hi = colorbars[0].get_ylim()
    assert hi == pytest.approx(0.1, rel=1e-6) and lo == pytest.approx(-0.1, rel=1e-6)
    assert "0.2 m/s" in text or "0.5 m/s" in text    # the arrow scale, a round number


def test_vector_png_in_mm_without_dt(captured):
    plots.vector_slices(_vectors(None), "unused.png", title="a -> b")
    text = _texts(captured[0])
    assert "displacement (mm)" in text and "m/s" not in text and "a -> b" in text
    colorbars = [ax for ax in captured[0].axes if ax.get_label() == "<colorbar>"]
    assert colorbars[0].get_ylim()[1] == pytest.approx(0.1, rel=1e-6)   # 1e-4 m = 0.1 mm


def test_volume_png_has_colour_bars_and_explained_markers(captured):
    vol = np.zeros((5, 6, 7), np.float32)
    vol[2, 3, 4] = 1.0
    x, y, z = (np.arange(n) * 1e-4 - 3e-4 for n in (7, 6, 5))
    particles = np.array([[x[4], y[3], z[2]]])
    plots.volume_slices(vol, x, y, z, "unused.png", particles=particles, title="volume A")
    fig = captured[0]
    colorbars = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert len(colorbars) == 2
    assert all("intensity" in ax.get_ylabel() for ax in colorbars)
    legends = [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None]
    assert legends and all("particles within one voxel" in lg.get_texts()[0].get_text()
                           for lg in legends)
