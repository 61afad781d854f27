"""What the figures show: the data behind the plots of ``liecontrol demo`` and ``liecontrol compare``
(shared bins, quantile bands inside the data's range, equal 3-D axes, the explanation of a return gap,
step ticks that do not collide, budgets as text) and that the figures render with it."""

from __future__ import annotations

import types

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from learning.evaluate import error_band
from liecontrol import compare, demo


def test_shared_bins_span_every_sample_and_skip_nan():
    a, b = np.array([-230.0, -220.0, np.nan]), np.array([-400.0, -150.0])
    edges = demo.shared_bins(a, b, bins=10)
    assert edges.size == 11 and edges[0] == -400.0 and edges[-1] == -150.0
    # both histograms drawn with these edges count every finite value
    assert np.histogram(a[np.isfinite(a)], edges)[0].sum() == 2 and np.histogram(b, edges)[0].sum() == 2


def test_quantile_band_of_nonnegative_errors_stays_nonnegative():
    rng = np.random.default_rng(0)
    c = np.abs(rng.standard_cauchy((50, 20)))          # heavy-tailed, nonnegative
    c[:, -1] = np.nan                                  # every episode has ended
    median, lo, hi = error_band(c)
    ok = slice(0, -1)
    assert (lo[ok] >= 0).all() and (lo[ok] <= median[ok]).all() and (median[ok] <= hi[ok]).all()
    assert ((c[:, ok].mean(0) - c[:, ok].std(0)) < 0).any()   # what mean ± std would have drawn
    assert np.isnan([median[-1], lo[-1], hi[-1]]).all()


def test_cube_limits_are_equal_and_hold_every_point():
    pts = np.array([[0.0, 0.0, 0.0], [2.0, 0.5, -0.1], [1.0, -0.5, 0.3]])
    lo, hi = demo.cube_limits(pts)
    assert np.allclose(hi - lo, (hi - lo)[0]) and (lo <= pts.min(0)).all() and (hi >= pts.max(0)).all()


def _duel(mpc_return, ppo_return, curves=None):
    def run(r):
        return types.SimpleNamespace(returns=np.array([r - 5.0, r + 5.0]),
                                     error_curve=np.abs(np.random.default_rng(1).normal(size=(2, 10))))
    m = {"success_rate": 1.0, "return_mean": mpc_return}
    p = {"success_rate": 0.5, "return_mean": ppo_return}
    return {"task": "PendulumSwingUp", "envs": 2, "ppo_steps": 64, "mpc": m, "ppo": p,
            "_mpc": run(mpc_return), "_ppo": run(ppo_return)}


def test_return_gap_note_only_when_the_mpc_is_below():
    assert demo.return_gap_note(_duel(-180.0, -230.0)) is None
    note = demo.return_gap_note(_duel(-230.0, -187.0), horizon=40)
    assert "-230" in note and "-187" in note and "40-step" in note and "100 %" in note and "50 %" in note
    assert "\n" not in note


@pytest.mark.parametrize("mpc_return, has_note", [(-230.0, True), (-180.0, False)])
def test_mpc_vs_ppo_figure_captions_the_gap(mpc_return, has_note):
    fig = Figure()
    FigureCanvasAgg(fig)
    a1, a2 = fig.subplots(1, 2)
    demo._plot_duel(fig, a1, a2, _duel(mpc_return, -187.0))
    texts = [t.get_text() for t in fig.texts]
    assert any("below PPO's" in t for t in texts) == has_note
    assert a2.get_ylim()[0] == 0
    labels = [t.get_text() for t in a2.get_legend().get_texts()]
    assert "MPC 10-90 % of episodes" in labels
    widths = {tuple(np.round([p.get_width() for p in c], 9)) for c in a1.containers}
    assert len(widths) == 1  # both histograms on the same bins


def test_step_ticks_skip_the_linear_part():
    assert compare.step_ticks(8192, 200_000) == [0.0, 1e4, 1e5]
    assert compare.step_ticks(100, 1000) == [0.0, 100.0, 1000.0]
    assert compare.step_ticks(1, 0) == [0.0]
    assert [compare._steps_label(x) for x in (0, 1e4, 2.5e6, 512)] == ["0", "10k", "2.5M", "512"]


def test_compare_report_prints_budgets_as_text():
    assert compare.budget_text({"ppo": 100000, "sac": 20000}) == "PPO 100000 steps, SAC 20000 steps"


def test_compare_curves_keep_success_within_0_and_100_percent(tmp_path, monkeypatch):
    st = [0, 8192, 16384, 200000]
    curve = {"steps": st, "return_mean": [-1500, -900, -400, -200], "return_min": [-1600, -1000, -500, -250],
             "return_max": [-1400, -800, -300, -150], "success_mean": [0, 0.2, 0.8, 1],
             "success_min": [0, 0, 0.6, 1], "success_max": [0, 0.4, 1, 1]}
    rec = {"env": "PendulumSwingUp", "seeds": [0], "mpc": {"return": {"mean": -230.0}, "success_rate": 1.0},
           "ppo": {"curve": curve}}
    seen = {}
    monkeypatch.setattr(Figure, "savefig", lambda self, *a, **k: seen.setdefault("fig", self))
    compare._plot(rec, ["ppo"], str(tmp_path / "curves.png"))
    returns_ax, success_ax = seen["fig"].axes
    assert success_ax.get_ylim() == (0, 100)
    for ax in (returns_ax, success_ax):
        assert list(ax.get_xticks()) == [0.0, 1e4, 1e5] and ax.get_xlim()[0] == 0
