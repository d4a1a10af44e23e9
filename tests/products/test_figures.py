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


# ---- layout: titles, arrow keys, colours, text that fits ------------------------------------

def _keys(fig):
    from matplotlib.quiver import QuiverKey

    return [(ax, a) for ax in fig.axes for a in ax.get_children() if isinstance(a, QuiverKey)]


def _key_box(key):
    """Display box of a quiver key: its arrow (offset + vertices) and its label."""
    from matplotlib.transforms import Bbox

    v = key.vector
    off = v.get_offset_transform().transform(v.get_offsets())
    pts = v.get_transform().transform(v.get_paths()[0].vertices) + off
    arrow = Bbox.from_extents(*pts.min(axis=0), *pts.max(axis=0))
    return Bbox.union([arrow, key.text.get_window_extent()])


def test_titles_never_double_a_word(captured):
    assert plots.title_text("pair pair", "velocity (m/s)") == "pair: velocity (m/s)"
    assert plots.title_text("pair p", "velocity (m/s)") == "pair p: velocity (m/s)"
    assert plots.title_text("pair pair: volume A") == "pair: volume A"
    assert plots.title_text("a: a") == "a: a"            # punctuation ends a run
    plots.vector_slices(_vectors(None), "unused.png", title="pair pair")
    assert captured[0]._suptitle.get_text() == "pair: displacement (mm)"


def test_pair_products_title_the_pair_once(tmp_path, monkeypatch):
    """save_pair's figures for a pair named "pair" (the demo's)."""
    from plenopiv.workflow import pair as pair_module
    from plenopiv.workflow import provenance

    titles = []
    for name in ("volume_provenance", "vectors_provenance", "mask_inputs"):
        monkeypatch.setattr(provenance, name, lambda *a, **k: {})
    monkeypatch.setattr(plots, "vector_slices",
                        lambda vec, path, *, title="": titles.append(plots.title_text(
                            title, "velocity (m/s)")) or path)
    monkeypatch.setattr(plots, "volume_slices",
                        lambda *a, title="", **k: titles.append(plots.title_text(title))
                        or a[4])

    class Vol:
        def __init__(self):
            from plenopiv.camera.grid import VolumeGrid

            self.grid = VolumeGrid((0, 0, 0), (1, 1, 1), (2, 2, 2))
            self.volume = np.zeros((2, 2, 2))
            self.particle_position_effective = np.zeros((0, 3))

        def save(self, path, config=None, **kw):
            return path

    class Vec:
        def save(self, path, **kw):
            return [path]

    class Exp:
        output = type("O", (), {"png": True, "vtk": False})()
        piv = None
        images = type("I", (), {"dt_s": None})()

        def to_dict(self):
            return {}

    res = pair_module.PairResult(Vol(), Vol(), Vec(), {})
    pair_module.save_pair(res, tmp_path, "pair", Exp())
    assert titles == ["pair: volume A", "pair: velocity (m/s)"]


@pytest.mark.parametrize("shape", [(4, 5, 6), (6, 3, 12), (5, 12, 4)])
def test_arrow_key_sits_outside_the_frame_and_inside_the_figure(captured, shape):
    nz, ny, nx = shape
    x, y, z = (np.linspace(-1e-3, 1e-3, n) for n in (nx, ny, nz))
    u = np.full(shape, 2.5e-4)
    vec = VectorResult(x, y, z, u, -0.4 * u, 0.3 * u, np.ones(shape, bool),
                       np.full(shape, 3.0))
    plots.vector_slices(vec, "unused.png", title="a -> b")
    fig = captured[0]
    fig.canvas.draw()
    keys = _keys(fig)
    assert len(keys) == 2
    for ax, key in keys:
        box, frame = _key_box(key), ax.get_window_extent()
        title = ax.title if ax.title.get_text() else ax._left_title
        assert fig.bbox.x0 <= box.x0 and box.x1 <= fig.bbox.x1
        assert box.y0 > frame.y1                              # above the frame, not on it
        assert box.y1 < title.get_window_extent().y0          # under the panel's title
        assert frame.x0 - 1 <= box.x0 and box.x1 <= frame.x1  # over the panel


def test_xz_arrows_show_the_motion_in_colour(captured):
    """A vortex about y: the x-z arrows are coloured by the speed over a perceptual map from
    0 to its robust top (their colours spread), the x-y ones by w, centred at 0."""
    shape = (9, 5, 9)
    x, y, z = (np.linspace(-1e-3, 1e-3, n) for n in (9, 5, 9))
    Z, _, X = np.meshgrid(z, y, x, indexing="ij")
    u, w = 0.2 * Z, -0.2 * X
    w = w.copy()
    w[0, 0, 0] = 5e-3                                   # one outlier does not wash it out
    vec = VectorResult(x, y, z, u, np.zeros(shape), w, np.ones(shape, bool),
                       np.full(shape, 3.0))
    plots.vector_slices(vec, "unused.png")
    fig = captured[0]
    xy, xz = (key.Q for _, key in _keys(fig))
    assert xz.get_cmap().name == "viridis" and xz.norm.vmin == 0
    shown = xz.norm(xz.get_array())
    assert np.ptp(shown) > 0.7                          # from dark to bright, not one grey
    assert xy.get_cmap().name == "RdBu_r" and xy.norm.vmin == -xy.norm.vmax
    assert xy.norm.vmax < 0.5 * 5                       # the outlier (5 mm) is clipped
    labels = [ax.get_ylabel() for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert labels[0].startswith("w, out-of-plane") and labels[1].startswith("speed")


def test_calibration_text_fits_the_figure(captured):
    """The calibration report's text panel wraps its lines to the figure's width."""
    plt, fig = plots._figure(figsize=(13, 9.5))
    for i in range(1, 4):
        fig.add_subplot(2, 2, i).plot([0, 1], [0, 1])
    long = ("  focal_point: square, rms 0.0123 px (0.07 % of pitch), 3 missing (0.1 %), "
            "2501 of 2501 spots fitted, 0 off-lattice, spot centres: window, phase bias "
            "0.0000 px")
    text = plots._text_panel(fig, fig.add_subplot(2, 2, 4), ["camera: small", long, "",
                                                              "kept: 100.000 mm (both)"])
    captured.append(fig)
    fig.canvas.draw()
    box = text.get_window_extent()
    assert fig.bbox.x0 <= box.x0 and box.x1 <= fig.bbox.x1
    shown = text.get_text().splitlines()
    assert len(shown) > 4 and shown[2].startswith("    ")          # wrapped, indented
    assert " ".join(s.strip() for s in shown[1:-2]) == long.strip()
