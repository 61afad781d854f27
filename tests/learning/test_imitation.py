"""learning.imitation: the imitation loss's gradient (implicit) against finite differences and unrolled
autograd, identifiability of the pendulum's (g/l, 1/(m l²)) and of the cart-pole's four parameters,
learning the dynamics from 10 demonstrations, unconverged and non-finite samples accounted for, baselines,
bad input, the example."""

import json
import math

import pytest
import torch

from controllers.ilqr import ILQROptions, ilqr
from controllers.problem import Reason
from learning.imitation import (
    control_jacobian,
    identifiable_combinations,
    imitation_loss,
    imitation_setup,
    imitation_study,
    learn_dynamics,
)

D64 = torch.float64
TIGHT = ILQROptions(max_iter=300, tol=1e-14, tol_cost=0.0, tol_kkt=1e-12)


def _data(system, N, seed=0, dtype=D64):
    setup = imitation_setup(system, dtype=dtype)
    x0 = setup.sample_starts(N, torch.Generator().manual_seed(seed))
    sol = ilqr(setup.problem(setup.expert_model(), x0), grad="none", options=TIGHT)
    assert sol.status.all_converged
    return setup, x0, sol.u


def _loss_of(setup, z, x0, ue, grad, u_init):
    params = dict(zip(setup.param_names, z.exp()))
    return imitation_loss(setup, params, x0, ue, u_init=u_init, grad=grad, options=TIGHT)


@pytest.mark.parametrize("system,point", [("pendulum", (12.0, 1.3, 0.9)),
                                          ("cartpole", (9.0, 1.2, 0.12, 0.45))])
def test_gradient_matches_finite_differences_and_unrolled(system, point):
    setup, x0, ue = _data(system, 3 if system == "pendulum" else 2)
    z = torch.tensor(point, dtype=D64).log().requires_grad_()
    res = _loss_of(setup, z, x0, ue, "implicit", ue)
    assert res.solution.status.all_converged and bool(res.included.all())
    g_imp, = torch.autograd.grad(res.loss, z)
    # the regime: some controls on their limits, most free (pendulum); a nonzero gradient
    assert float(g_imp.abs().max()) > 1e-3
    h = 1e-5
    fd = torch.zeros_like(g_imp)
    with torch.no_grad():
        for i in range(z.numel()):
            e = torch.zeros_like(z)
            e[i] = h
            lp = _loss_of(setup, z.detach() + e, x0, ue, "none", ue).loss
            lm = _loss_of(setup, z.detach() - e, x0, ue, "none", ue).loss
            fd[i] = (lp - lm) / (2 * h)
    scale = float(g_imp.abs().max())
    assert torch.allclose(g_imp, fd, rtol=0, atol=1e-6 * scale), (g_imp, fd)
    z2 = z.detach().clone().requires_grad_()
    res_u = _loss_of(setup, z2, x0, ue, "unrolled", ue)
    g_unr, = torch.autograd.grad(res_u.loss, z2)
    assert torch.allclose(g_imp, g_unr, rtol=0, atol=1e-7 * scale), (g_imp, g_unr)


def test_pendulum_equal_identifiable_combinations_give_identical_actions():
    setup, x0, _ = _data("pendulum", 6, seed=3)

    def actions(g, m, l_):
        model = setup.model({"gravity": g, "mass": m, "length": l_})
        return ilqr(setup.problem(model, x0), grad="none", options=TIGHT).u

    u = actions(10.0, 1.0, 1.0)
    # (g, m, l) -> (k g, m / k², k l) keeps g/l and 1/(m l²): with k = 2 every product is exact in binary
    assert (actions(20.0, 0.25, 2.0) - u).abs().max() <= 1e-12
    k = 1.7  # the same model up to rounding: the plans agree to the solver's tolerance
    assert (actions(10.0 * k, 1.0 / k**2, k) - u).abs().max() <= 1e-8
    a = identifiable_combinations("pendulum", {"gravity": 10.0 * k, "mass": 1.0 / k**2, "length": k})
    assert a["g/l"] == pytest.approx(10.0, rel=1e-14) and a["1/(m l^2)"] == pytest.approx(1.0, rel=1e-14)
    # while a 1 % change of g/l is seen in the controls
    assert (actions(10.1, 1.0, 1.0) - u).abs().max() > 1e-3


def test_control_jacobian_rank_pendulum_2_cartpole_4():
    setup, x0, ue = _data("pendulum", 2)
    J = control_jacobian(setup, setup.true_params, x0, ue, options=TIGHT)
    assert J.shape == (2 * 20, 3)
    s = torch.linalg.svdvals(J)
    assert s[1] / s[0] > 1e-3 and s[2] / s[0] < 1e-9
    null = torch.tensor([1.0, -2.0, 1.0], dtype=D64)  # d log(g, m, l) keeping g/l and m l²
    assert (J @ null).abs().max() <= 1e-9 * s[0]
    setup, x0, ue = _data("cartpole", 2)
    s = torch.linalg.svdvals(control_jacobian(setup, setup.true_params, x0, ue, options=TIGHT))
    assert s[3] / s[0] > 1e-4


def test_learn_pendulum_from_10_demos_within_1_percent():
    r = learn_dynamics("pendulum", 10, 0, baselines=(), n_test=10, steps=40)
    assert r["identifiable"] == ["g/l", "1/(m l^2)"]
    assert r["identifiable_rel_err_max"] < 0.01
    assert max(r["param_rel_err"][k] for k in r["identifiable"]) == r["identifiable_rel_err_max"]
    # the learned physical parameters reproduce the identifiable combinations they are judged on
    c = identifiable_combinations("pendulum", r["params"])
    assert c["g/l"] == pytest.approx(10.0, rel=0.01) and c["1/(m l^2)"] == pytest.approx(1.0, rel=0.01)
    assert r["imitation_mse"] < 1e-3 * r["imitation_mse_init"]
    h = r["history"]
    assert len(h["loss"]) == r["evaluations"] == len(h["n_unconverged"]) <= 40
    assert h["identifiable_rel_err_max"][0] == pytest.approx(2.0)  # g/l starts at 30 against 10
    assert min(h["loss"]) < 1e-6 * h["loss"][0]
    assert r["unconverged"]["sample_solves"] == sum(h["n_unconverged"])
    json.dumps(r)


def test_unconverged_samples_counted_included_or_excluded():
    setup, x0, ue = _data("pendulum", 4)
    # warm start: the expert's plan for the first two samples (already optimal), zeros for the others;
    # one iteration leaves the others unconverged
    u_init = torch.cat([ue[:2], torch.zeros_like(ue[2:])])
    one = ILQROptions(max_iter=1)
    params = dict(setup.true_params)
    inc = imitation_loss(setup, params, x0, ue, u_init=u_init, options=one, unconverged="include")
    exc = imitation_loss(setup, params, x0, ue, u_init=u_init, options=one, unconverged="exclude")
    conv = inc.solution.status.converged
    assert conv.tolist() == [True, True, False, False]
    assert inc.included.all() and exc.included.tolist() == conv.tolist()
    assert torch.allclose(inc.loss, inc.per_sample.mean())
    assert torch.allclose(exc.loss, exc.per_sample[conv].mean())
    for policy in ("include", "exclude"):
        r = learn_dynamics("pendulum", 4, 0, steps=3, options=one, unconverged=policy, baselines=(), n_test=2,
                           warm_start="previous")
        h = r["history"]
        assert h["n_unconverged"][0] > 0
        assert all(len(s) == n for s, n in zip(h["unconverged_samples"], h["n_unconverged"]))
        assert set(sum(h["unconverged_reasons"], [])) <= {"MAX_ITERATIONS", "STALLED"}
        excl = h["n_unconverged"] if policy == "exclude" else [0] * len(h["n_unconverged"])
        assert h["n_excluded"] == excl
        assert r["unconverged"]["sample_solves"] == sum(h["n_unconverged"]) > 0
        assert r["unconverged"]["excluded"] == sum(excl)


def test_nonfinite_sample_does_not_poison_the_loss():
    setup, x0, ue = _data("pendulum", 3)
    x0 = x0.clone()
    x0[1, 0] = math.nan
    z = torch.tensor([12.0, 1.3, 0.9], dtype=D64).log().requires_grad_()
    res = imitation_loss(setup, dict(zip(setup.param_names, z.exp())), x0, ue, u_init=ue)
    assert int(res.solution.status.reason[1]) == int(Reason.NONFINITE_INPUT)
    assert res.included.tolist() == [True, False, True] and math.isnan(float(res.per_sample[1]))
    g, = torch.autograd.grad(res.loss, z)
    assert torch.isfinite(res.loss) and torch.isfinite(g).all()
    ref = imitation_loss(setup, dict(zip(setup.param_names, z.detach().exp())), x0[[0, 2]], ue[[0, 2]],
                         u_init=ue[[0, 2]])
    # the non-finite sample counts as the largest error within the limits, (2 u_max)², without a gradient
    worst = (2 * setup.u_limit) ** 2
    assert torch.allclose(res.loss.detach(), (2 * ref.loss + worst) / 3, rtol=1e-12, atol=0)
    z2 = z.detach().clone().requires_grad_()
    ref2 = imitation_loss(setup, dict(zip(setup.param_names, z2.exp())), x0[[0, 2]], ue[[0, 2]],
                          u_init=ue[[0, 2]])
    g_ref, = torch.autograd.grad(ref2.loss, z2)
    assert torch.allclose(g, 2 * g_ref / 3, rtol=1e-8, atol=1e-14)


def test_batched_loss_equals_per_sample_and_float32_close():
    setup, x0, ue = _data("pendulum", 3)
    params = {"gravity": 12.0, "mass": 1.3, "length": 0.9}
    res = imitation_loss(setup, params, x0, ue, u_init=ue, options=TIGHT)
    for i in range(3):
        one = imitation_loss(setup, params, x0[i:i + 1], ue[i:i + 1], u_init=ue[i:i + 1], options=TIGHT)
        assert torch.allclose(one.per_sample[0], res.per_sample[i], rtol=1e-9, atol=1e-14)
    s32 = imitation_setup("pendulum", dtype=torch.float32)
    r32 = imitation_loss(s32, params, x0.float(), ue.float(), u_init=ue.float())
    assert r32.loss.dtype == torch.float32
    assert float(r32.loss) == pytest.approx(float(res.loss), rel=1e-3)


def test_baselines_and_non_realizable_record():
    r = learn_dynamics("pendulum", 6, 1, steps=15, bc_epochs=30, n_test=4, expert_damping=0.5)
    assert not r["realizable"] and r["params_true"]["b/(m l^2)"] == pytest.approx(0.5)
    assert set(r["baselines"]) == {"sysid", "mlp", "lstm"}
    for k in ("mlp", "lstm"):
        assert r["baselines"][k]["imitation_mse"] >= 0
    # non-realizable: no exact fit, but better than the initial model
    assert 0 < r["imitation_mse"] < r["imitation_mse_init"]
    json.dumps(r)
    # system identification on realizable, noise-free transitions is exact in the identifiable combinations
    r = learn_dynamics("pendulum", 4, 2, steps=2, baselines=("sysid",), n_test=2)
    assert r["baselines"]["sysid"]["identifiable_rel_err_max"] < 1e-8
    assert r["baselines"]["sysid"]["imitation_mse"] < 1e-10


def test_imitation_study_order():
    recs = imitation_study("pendulum", n_trains=(2, 3), seeds=(0, 1), steps=2, baselines=(), n_test=2)
    assert [(r["n_train"], r["seed"]) for r in recs] == [(2, 0), (2, 1), (3, 0), (3, 1)]
    assert all(r["system"] == "pendulum" for r in recs)


@pytest.mark.parametrize("kw,exc,match", [
    (dict(system="acrobot"), ValueError, "system"),
    (dict(n_train=0), ValueError, "n_train"),
    (dict(seed=-1), ValueError, "seed"),
    (dict(steps=0), ValueError, "steps"),
    (dict(unconverged="drop"), ValueError, "unconverged"),
    (dict(warm_start="zeros"), ValueError, "warm_start"),
    (dict(optimizer="sgd"), ValueError, "optimizer"),
    (dict(baselines="mlp"), ValueError, "baselines"),
    (dict(system="cartpole", expert_damping=0.1), ValueError, "expert_damping"),
    (dict(expert_damping=-1.0), ValueError, "expert_damping"),
    (dict(options="tight"), TypeError, "options"),
    (dict(dtype=torch.int64), TypeError, "dtype"),
])
def test_learn_dynamics_bad_input(kw, exc, match):
    args = dict(system="pendulum", n_train=2, seed=0, steps=1, baselines=(), n_test=1)
    args.update(kw)
    system, n, seed = args.pop("system"), args.pop("n_train"), args.pop("seed")
    with pytest.raises(exc, match=match):
        learn_dynamics(system, n, seed, **args)


def test_imitation_loss_bad_input():
    setup, x0, ue = _data("pendulum", 2)
    with pytest.raises(ValueError, match="u_expert"):
        imitation_loss(setup, setup.true_params, x0, ue[:, :5])
    with pytest.raises(ValueError, match="x0"):
        imitation_loss(setup, setup.true_params, x0[0], ue)
    with pytest.raises(ValueError, match="unconverged"):
        imitation_loss(setup, setup.true_params, x0, ue, unconverged="maybe")
    with pytest.raises(ValueError, match="lacks"):
        setup.model({"gravity": 1.0})
    with pytest.raises(TypeError, match="generator"):
        setup.sample_starts(2, 0)


def test_example_imitation_dynamics(tmp_path):
    from examples.learning.imitation_dynamics import run

    res = run(tmp_path)
    assert res["checks"] and all(res["checks"].values()), res
    assert (tmp_path / "imitation_dynamics.png").exists()
    v = res["values"]
    assert max(v["rel_err_g_over_l"], v["rel_err_inv_ml2"]) < 0.01
    assert v["imitation_mse"] < 1e-6 * v["imitation_mse_init"]
    json.dumps(res)
