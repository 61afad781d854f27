"""learning.imitation, adversarial: bad arguments refused by name, dtype never silently changed, a non-finite
sample never poisons the gradient of the others, unconverged solves included by default (counted) or excluded
and counted, gradcheck of the imitation loss in float64, batched == per-sample gradients, determinism, and
strictly JSON-able records whose non-finite values are reported."""

import json
import math

import pytest
import torch

from controllers.ilqr import ILQROptions, ilqr
from learning.demos import expert_demos
from learning.imitation import (
    behaviour_cloning,
    control_jacobian,
    identifiable_combinations,
    imitation_loss,
    imitation_setup,
    imitation_study,
    learn_dynamics,
    system_identification,
)

D64 = torch.float64
TIGHT = ILQROptions(max_iter=300, tol=1e-14, tol_cost=0.0, tol_kkt=1e-12)
FAST = dict(baselines=(), n_test=2, steps=2)


@pytest.fixture(scope="module")
def pend():
    setup = imitation_setup("pendulum")
    x0 = setup.sample_starts(3, torch.Generator().manual_seed(0))
    sol = ilqr(setup.problem(setup.expert_model(), x0), grad="none", options=TIGHT)
    assert sol.status.all_converged
    return setup, x0, sol.u


def _params(setup, z):
    return dict(zip(setup.param_names, z.exp()))


# ------------------------------------------------------------------------------------------------ defaults


def test_exclude_policy_drops_unconverged_samples(pend):
    """unconverged='exclude' (not the default here: the module docstring says why) leaves non-converged
    samples out of the mean; the default 'include' keeps them, counted."""
    setup, x0, ue = pend
    u_init = torch.cat([ue[:2], torch.zeros_like(ue[2:])])
    kw = dict(u_init=u_init, options=ILQROptions(max_iter=1))
    res = imitation_loss(setup, setup.true_params, x0, ue, unconverged="exclude", **kw)
    conv = res.solution.status.converged
    assert conv.tolist() == [True, True, False]
    assert res.included.tolist() == conv.tolist()
    assert torch.allclose(res.loss, res.per_sample[conv].mean())
    inc = imitation_loss(setup, setup.true_params, x0, ue, **kw)  # the default
    assert inc.included.all() and torch.allclose(inc.loss, inc.per_sample.mean())
    r = learn_dynamics("pendulum", 3, 0, options=ILQROptions(max_iter=1), warm_start="previous",
                       unconverged="exclude", **dict(FAST, steps=4))
    assert r["unconverged"]["policy"] == "exclude"
    h = r["history"]
    assert h["n_excluded"] == h["n_unconverged"]
    assert r["unconverged"]["excluded"] == r["unconverged"]["sample_solves"] > 0
    # every sample excluded: no gradient information -- the fit stops where it is, never a NaN step
    assert set(sum(h["unconverged_reasons"], [])) <= {"MAX_ITERATIONS", "STALLED"}
    assert r["nonfinite_values"] == [] and r["params"] == pytest.approx(r["params_init"])


def test_all_excluded_is_never_a_perfect_fit(pend):
    setup, x0, ue = pend
    res = imitation_loss(setup, setup.true_params, x0, ue, options=ILQROptions(max_iter=1),
                         unconverged="exclude")
    assert not res.solution.status.converged.any() and not res.included.any()
    # no usable sample: the largest error within the limits, not 0
    assert float(res.loss) == pytest.approx((2 * setup.u_limit) ** 2)


# --------------------------------------------------------------------------------------- non-finite samples


def test_diverged_samples_give_finite_zero_gradient(pend):
    setup, x0, ue = pend
    # parameters where every rollout diverges (SINGULAR_QUU / non-finite plans)
    z = torch.tensor([1e25, 1e-30, 1e-5], dtype=D64).log().requires_grad_()
    res = imitation_loss(setup, _params(setup, z), x0, ue, u_init=ue)
    assert not torch.isfinite(res.solution.u).all()
    assert torch.isnan(res.per_sample).all() and not res.included.any()
    assert float(res.loss) == pytest.approx((2 * setup.u_limit) ** 2)
    if res.loss.requires_grad:
        g, = torch.autograd.grad(res.loss, z, allow_unused=True)
        assert g is None or (torch.isfinite(g).all() and (g == 0).all()), g


def test_one_diverged_sample_does_not_poison_the_others_gradient(pend):
    setup, x0, ue = pend
    z = torch.tensor([12.0, 1.3, 0.9], dtype=D64).log().requires_grad_()
    u_init = ue.clone()
    u_init[1] = math.inf  # a non-finite warm start for one sample only
    res = imitation_loss(setup, _params(setup, z), x0, ue, u_init=u_init, options=TIGHT)
    assert res.included.tolist() == [True, False, True]
    g, = torch.autograd.grad(res.loss, z)
    z2 = z.detach().clone().requires_grad_()
    ref = imitation_loss(setup, _params(setup, z2), x0[[0, 2]], ue[[0, 2]], u_init=ue[[0, 2]], options=TIGHT)
    g_ref, = torch.autograd.grad(ref.loss, z2)
    assert torch.allclose(g, 2 * g_ref / 3, rtol=1e-8, atol=1e-14)


def test_nonfinite_demo_controls_reported_per_sample_as_nan(pend):
    setup, x0, ue = pend
    z = torch.tensor([12.0, 1.3, 0.9], dtype=D64).log().requires_grad_()
    for bad in (math.nan, math.inf, 1e300):
        u2 = ue.clone()
        u2[0, 3, 0] = bad
        res = imitation_loss(setup, _params(setup, z), x0, u2, u_init=ue, options=TIGHT)
        assert math.isnan(float(res.per_sample[0])) and res.included.tolist() == [False, True, True]
        g, = torch.autograd.grad(res.loss, z)
        assert torch.isfinite(g).all()


def test_adam_with_a_huge_step_never_gives_nan_parameters_and_the_record_is_strict_json():
    r = learn_dynamics("pendulum", 2, 0, optimizer="adam", lr=50.0, baselines=(), n_test=2, steps=3)
    for v in r["params"].values():
        assert v is None or math.isfinite(v)
    assert all(math.isfinite(v) for v in sum(r["history"]["params"].values(), []) if v is not None)
    json.dumps(r, allow_nan=False)
    assert isinstance(r["nonfinite_values"], list)


def test_record_reports_nonfinite_values_instead_of_nan():
    # lr=700: exp(log theta) overflows -> inf parameters; they are reported, replaced by None
    r = learn_dynamics("pendulum", 2, 0, optimizer="adam", lr=700.0, baselines=(), n_test=2, steps=3)
    s = json.dumps(r, allow_nan=False)
    assert "NaN" not in s and "Infinity" not in s
    for path in r["nonfinite_values"]:
        assert isinstance(path, str) and path
    assert ("params" in " ".join(r["nonfinite_values"])) == any(v is None for v in r["params"].values())


# ------------------------------------------------------------------------------------------------ gradients


def test_gradcheck_imitation_loss_wrt_log_params(pend):
    setup, x0, ue = pend
    x0, ue = x0[:2], ue[:2]

    def f(z):
        return imitation_loss(setup, _params(setup, z), x0, ue, u_init=ue, options=TIGHT).loss

    z = torch.tensor([12.0, 1.3, 0.9], dtype=D64).log().requires_grad_()
    assert torch.autograd.gradcheck(f, (z,), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_batched_gradient_equals_per_sample_loop_and_tensor_params_equal_floats(pend):
    setup, x0, ue = pend
    z = torch.tensor([12.0, 1.3, 0.9], dtype=D64).log().requires_grad_()
    loss = imitation_loss(setup, _params(setup, z), x0, ue, u_init=ue, options=TIGHT).loss
    g, = torch.autograd.grad(loss, z)
    gs = []
    for i in range(3):
        zi = z.detach().clone().requires_grad_()
        li = imitation_loss(setup, _params(setup, zi), x0[i:i + 1], ue[i:i + 1], u_init=ue[i:i + 1],
                            options=TIGHT).loss
        gs.append(torch.autograd.grad(li, zi)[0])
    assert torch.allclose(g, torch.stack(gs).mean(0), rtol=1e-9, atol=1e-14)
    floats = dict(zip(setup.param_names, z.detach().exp().tolist()))
    a = imitation_loss(setup, floats, x0, ue, u_init=ue, options=TIGHT).loss
    b = imitation_loss(setup, _params(setup, z.detach()), x0, ue, u_init=ue, options=TIGHT).loss
    assert float(a) == pytest.approx(float(b), rel=1e-13)
    # per-sample parameter tensors (N,) equal to the shared ones
    per = {k: v.expand(3) for k, v in _params(setup, z.detach()).items()}
    assert float(imitation_loss(setup, per, x0, ue, u_init=ue, options=TIGHT).loss) == pytest.approx(float(a))


def test_null_direction_also_at_the_learners_start(pend):
    setup, x0, ue = pend
    J = control_jacobian(setup, setup.init_params, x0[:2], ue[:2], options=TIGHT)
    s = torch.linalg.svdvals(J)
    null = torch.tensor([1.0, -2.0, 1.0], dtype=D64)
    assert (J @ null).abs().max() <= 1e-9 * s[0] and s[1] / s[0] > 1e-4


def test_float32_follows_inputs(pend):
    _, x0, ue = pend
    s32 = imitation_setup("pendulum", dtype=torch.float32)
    z = torch.tensor([12.0, 1.3, 0.9], dtype=torch.float32).log().requires_grad_()
    res = imitation_loss(s32, _params(s32, z), x0.float(), ue.float(), u_init=ue.float())
    g, = torch.autograd.grad(res.loss, z)
    assert res.loss.dtype == g.dtype == res.per_sample.dtype == torch.float32
    J = control_jacobian(s32, s32.true_params, x0[:1].float(), ue[:1].float())
    assert J.dtype == torch.float32


# ------------------------------------------------------------------------------------ unconverged / Jacobian


def test_control_jacobian_marks_unconverged_and_nonfinite_rows(pend):
    setup, x0, ue = pend
    u_init = ue.clone()
    u_init[2] = 0.0
    one = ILQROptions(max_iter=1)
    J = control_jacobian(setup, setup.true_params, x0, u_init, options=one)
    T = setup.horizon
    assert torch.isfinite(J[:2 * T]).all() and torch.isnan(J[2 * T:]).all()
    J_inc = control_jacobian(setup, setup.true_params, x0, u_init, options=one, unconverged="include")
    assert torch.isfinite(J_inc).all()
    x_bad = x0.clone()
    x_bad[0, 1] = math.nan
    J = control_jacobian(setup, setup.true_params, x_bad, ue, options=TIGHT, unconverged="include")
    assert torch.isnan(J[:T]).all() and torch.isfinite(J[T:]).all()


def test_learn_dynamics_is_deterministic_and_n_train_1_runs():
    a = learn_dynamics("pendulum", 1, 3, baselines=("sysid", "mlp"), bc_epochs=3, n_test=1, steps=2)
    b = learn_dynamics("pendulum", 1, 3, baselines=("sysid", "mlp"), bc_epochs=3, n_test=1, steps=2)
    for r in (a, b):
        for k in ("time_s", "time_learn_s"):
            r.pop(k)
        for v in r["baselines"].values():
            v.pop("time_s")
    assert a == b
    json.dumps(a, allow_nan=False)


# ------------------------------------------------------------------------------------------------ bad input


@pytest.mark.parametrize("params,exc,match", [
    (None, TypeError, "params"),
    ({"gravity": 10.0}, ValueError, "lacks"),
    ({"gravity": 10.0, "mass": 1.0, "length": 1.0, "damping": 0.5}, ValueError, "damping"),
    ({"gravity": math.nan, "mass": 1.0, "length": 1.0}, ValueError, "gravity"),
    ({"gravity": 10.0, "mass": 0.0, "length": 1.0}, ValueError, "mass"),
    ({"gravity": 10.0, "mass": -1.0, "length": 1.0}, ValueError, "mass"),
    ({"gravity": 10.0, "mass": 1.0, "length": math.inf}, ValueError, "length"),
    ({"gravity": 10.0, "mass": 1.0, "length": "1"}, TypeError, "length"),
    ({"gravity": 10.0, "mass": 1.0, "length": True}, TypeError, "length"),
    ({"gravity": 10.0, "mass": 1.0, "length": torch.tensor(1.0)}, TypeError, "length"),
    ({"gravity": 10.0, "mass": 1.0, "length": torch.ones(2, dtype=D64)}, ValueError, "length"),
])
def test_imitation_loss_and_jacobian_refuse_bad_params(pend, params, exc, match):
    setup, x0, ue = pend
    with pytest.raises(exc, match=match):
        imitation_loss(setup, params, x0, ue)
    with pytest.raises(exc, match=match):
        control_jacobian(setup, params, x0)


def test_imitation_loss_refuses_bad_data(pend):
    setup, x0, ue = pend
    P = setup.true_params
    with pytest.raises(TypeError, match="setup"):
        imitation_loss("pendulum", P, x0, ue)
    with pytest.raises(TypeError, match="x0.*float64"):
        imitation_loss(setup, P, x0.float(), ue.float())
    with pytest.raises(TypeError, match="u_expert.*float64"):
        imitation_loss(setup, P, x0, ue.float())
    with pytest.raises(TypeError, match="x0"):
        imitation_loss(setup, P, x0.long(), ue)
    with pytest.raises(ValueError, match="x0"):
        imitation_loss(setup, P, x0[:0], ue[:0])
    with pytest.raises(ValueError, match="u_expert"):
        imitation_loss(setup, P, x0, ue[:1])
    with pytest.raises(TypeError, match="options"):
        imitation_loss(setup, P, x0, ue, options="tight")
    with pytest.raises(ValueError, match="unconverged"):
        control_jacobian(setup, P, x0, unconverged="drop")
    with pytest.raises(ValueError, match="x0"):
        control_jacobian(setup, P, x0[:0])
    with pytest.raises(TypeError, match="setup"):
        control_jacobian("pendulum", P, x0)
    with pytest.raises(TypeError, match="options"):
        control_jacobian(setup, P, x0, options="tight")
    with pytest.raises(ValueError, match="device"):
        imitation_setup("pendulum", device="bogus")
    with pytest.raises(ValueError, match="count"):
        setup.sample_starts(-1, torch.Generator())
    with pytest.raises(ValueError, match="count"):
        setup.sample_starts(2.7, torch.Generator())


def test_identifiable_combinations_refuses_bad_params():
    with pytest.raises(ValueError, match="params.*mass"):
        identifiable_combinations("pendulum", {"gravity": 1.0})
    with pytest.raises(TypeError, match="params"):
        identifiable_combinations("pendulum", None)
    with pytest.raises(ValueError, match="mass"):
        identifiable_combinations("pendulum", {"gravity": 1.0, "mass": 0.0, "length": 1.0})
    with pytest.raises(ValueError, match="length"):
        identifiable_combinations("pendulum", {"gravity": 1.0, "mass": 1.0, "length": math.nan})
    with pytest.raises(ValueError, match="params.*cart_mass"):
        identifiable_combinations("cartpole", {"gravity": 1.0, "mass": 1.0, "length": 1.0})
    # extra names (a record's params_true with its damping) are read past; tensors pass through
    c = identifiable_combinations("pendulum", {"gravity": 10.0, "mass": 1.0, "length": 2.0, "damping": 0.5})
    assert c == {"g/l": 5.0, "1/(m l^2)": 0.25}
    t = identifiable_combinations("pendulum", {"gravity": torch.tensor(10.0), "mass": torch.tensor(1.0),
                                               "length": torch.tensor(2.0)})
    assert isinstance(t["g/l"], torch.Tensor)


def test_system_identification_refuses_bad_input(pend):
    setup, x0, _ = pend
    demos = expert_demos(setup.problem(setup.expert_model(), x0[:2]), keep="all")
    with pytest.raises(ValueError, match="steps"):
        system_identification(setup, demos, steps=0)
    with pytest.raises(ValueError, match="tol"):
        system_identification(setup, demos, tol=math.nan)
    with pytest.raises(TypeError, match="setup"):
        system_identification("pendulum", demos)
    with pytest.raises(ValueError, match="demos.*4"):
        system_identification(imitation_setup("cartpole"), demos)
    with pytest.raises(TypeError, match="demos.*float64"):
        system_identification(setup, demos.to(dtype=torch.float32))


def test_behaviour_cloning_refuses_bad_input(pend):
    setup, x0, ue = pend
    xt, ut = x0[:2], ue[:2]
    for kw, exc, match in [(dict(epochs=0), ValueError, "epochs"), (dict(epochs=2.5), ValueError, "epochs"),
                           (dict(lr=math.nan), ValueError, "lr"), (dict(hidden=1), ValueError, "hidden"),
                           (dict(seed="a"), ValueError, "seed"), (dict(kind="gru"), ValueError, "kind")]:
        with pytest.raises(exc, match=match):
            behaviour_cloning(setup, x0, ue, xt, ut, **kw)
    with pytest.raises(ValueError, match="u_expert"):
        behaviour_cloning(setup, x0, ue[:1], xt, ut, epochs=1)
    with pytest.raises(ValueError, match="u_test"):
        behaviour_cloning(setup, x0, ue, xt, ut[:1], epochs=1)
    with pytest.raises(ValueError, match="x0"):
        behaviour_cloning(setup, x0[0], ue[0], xt, ut, epochs=1)
    with pytest.raises(TypeError, match="x0"):
        behaviour_cloning(setup, x0.float(), ue, xt, ut, epochs=1)
    u_nan = ue.clone()
    u_nan[1, 4, 0] = math.nan
    with pytest.raises(ValueError, match="u_expert.*demo 1"):
        behaviour_cloning(setup, x0, u_nan, xt, ut, epochs=1)


def test_learn_dynamics_and_study_refuse_bad_input_before_running(monkeypatch):
    with pytest.raises(TypeError, match="baselines"):
        learn_dynamics("pendulum", 2, 0, baselines=None, steps=1, n_test=1)
    calls = []
    import learning.imitation as im
    orig = im.learn_dynamics
    with monkeypatch.context() as mp:
        mp.setattr(im, "learn_dynamics", lambda *a, **k: calls.append(a) or orig(*a, **k))
        for n_trains, seeds, kw, exc, match in [
            ((2, 0), (0,), {}, ValueError, "n_train"),
            ((2,), (0, -1), {}, ValueError, "seed"),
            ((2,), (0,), dict(bogus=1), TypeError, "bogus"),
            ((2,), (0,), dict(n_train=3), TypeError, "n_train"),
            ((2,), (0,), dict(lr=-1.0), ValueError, "lr"),
            ((2,), (0,), dict(u_limit=0.0), ValueError, "u_limit"),
        ]:
            with pytest.raises(exc, match=match):
                imitation_study("pendulum", n_trains, seeds, **dict(FAST, **kw))
        assert calls == []  # nothing ran before the error
    recs = imitation_study("pendulum", (n for n in (2,)), iter((0,)), **FAST)
    assert [(r["n_train"], r["seed"]) for r in recs] == [(2, 0)]
