"""Adversarial regression tests for learning.demos (issue 26 §1): each test pins a defect found by probing the
module as a user would (bad files, bad arguments, extreme settings).  They fail before the fix."""

import io
import math
import zipfile

import numpy as np
import pytest
import torch

from learning.demos import FORMAT, Demonstrations, handwriting, spatial_noise, time_warp


def _x(N=3, T=6, n=2, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(N, T, n, generator=g, dtype=torch.float64).to(dtype)


def _base_arrays():
    return {"format": np.array(FORMAT), "format_version": np.array(1, dtype=np.int64),
            "x": _x().numpy(), "dt": np.array(0.1), "meta_json": np.array("{}")}


def _write(path, **changes):
    a = {**_base_arrays(), **changes}
    with open(path, "wb") as f:
        np.savez(f, **a)
    return path


# ------------------------------------------------------------------------------------- .npz loading
@pytest.mark.parametrize("dt", [np.array("0.25"), np.array(True), np.array([0.1, 0.2, 0.3]), np.array([0.1])],
                         ids=["string", "bool", "shape3", "shape1"])
def test_load_rejects_malformed_dt_key(tmp_path, dt):
    # today: a string or bool 'dt' is silently converted (0.25, 1.0); a non-0-d one raises numpy's bare
    # "only 0-dimensional arrays can be converted" TypeError that names neither the key nor the file
    with pytest.raises(ValueError, match="'dt'"):
        Demonstrations.load(_write(tmp_path / "d.npz", dt=dt))


@pytest.mark.parametrize("ver", [np.array("abc"), np.array([1, 1]), np.array(1.7)],
                         ids=["str", "shape2", "float"])
def test_load_rejects_malformed_format_version(tmp_path, ver):
    # today: int("abc") ValueError without the key, numpy's TypeError for (2,), and 1.7 silently read as 1
    with pytest.raises(ValueError, match="format_version|format version"):
        Demonstrations.load(_write(tmp_path / "d.npz", format_version=ver))


def test_load_plain_npy_or_broken_file_is_a_clear_error(tmp_path):
    np.save(tmp_path / "plain.npy", np.zeros(3))
    # today: TypeError "'numpy.ndarray' object does not support the context manager protocol"
    with pytest.raises(ValueError, match="not a liecontrol.Demonstrations file"):
        Demonstrations.load(tmp_path / "plain.npy")
    good = tmp_path / "good.npz"
    Demonstrations(x=_x(), dt=0.1).save(good)
    (tmp_path / "trunc.npz").write_bytes(good.read_bytes()[:200])
    # today: zipfile.BadZipFile (neither ValueError nor naming the file)
    with pytest.raises(ValueError, match="trunc.npz"):
        Demonstrations.load(tmp_path / "trunc.npz")


def test_load_member_that_is_not_an_npy_array_names_the_key(tmp_path):
    p = tmp_path / "raw.npz"
    with zipfile.ZipFile(p, "w") as z:
        for k, v in _base_arrays().items():
            b = io.BytesIO()
            np.save(b, v)
            z.writestr(k + ".npy", b.getvalue())
        z.writestr("frame/p.npy", b"\x80\x04not an npy array")  # e.g. a pickle stored under an .npy name
    # today: AttributeError: 'bytes' object has no attribute 'dtype'
    with pytest.raises(ValueError, match="frame/p"):
        Demonstrations.load(p)


def test_load_object_array_error_names_the_key(tmp_path):
    p = _write(tmp_path / "o.npz", x=np.array([1, "a", None], dtype=object))
    # today: numpy's "Object arrays cannot be loaded when allow_pickle=False" (no key, no file)
    with pytest.raises(ValueError, match="'x'"):
        Demonstrations.load(p)


# ------------------------------------------------------------------------------------- from_arrays
def test_from_arrays_ragged_nested_list_names_the_demo():
    states = [[[0.0, 1.0], [1.0, 2.0]], [[0.0, 1.0], [1.0, 2.0]], [[0.0, 1.0], [1.0]]]
    # today: numpy's "inhomogeneous shape" ValueError, without the demo index
    with pytest.raises(ValueError, match=r"states\[2\]"):
        Demonstrations.from_arrays(states, dt=0.1)


@pytest.mark.parametrize("dt", [[True, True, True], ["0.1", "0.1", "0.1"], "0.1"],
                         ids=["bools", "strings", "str"])
def test_from_arrays_dt_sequence_must_be_numbers(dt):
    xs = [np.zeros((4, 1))] * (1 if isinstance(dt, str) else 3)
    # today: accepted silently (dt = 1.0 / 0.1); a scalar bool dt is rejected, a list of them is not
    with pytest.raises(TypeError, match="dt"):
        Demonstrations.from_arrays(xs, dt=dt)


# ------------------------------------------------------------------------------------- variability
@pytest.mark.parametrize("dtype,strength", [(torch.float32, 100.0), (torch.float64, 1000.0)])
def test_time_warp_large_strength_does_not_overflow(dtype, strength):
    x = torch.linspace(0, 1, 50, dtype=dtype)[None, :, None].expand(4, 50, 1).clone()
    d = Demonstrations(x=x, dt=0.1)
    # today: exp(g) overflows, τ = inf/inf = NaN and the error blames "field 'x' has a non-finite value";
    # the rate is scale-free (τ is normalized), so exp(g - max g) gives the same clock without overflow
    try:
        w, tau = time_warp(d, strength, torch.Generator().manual_seed(1), return_phase=True)
    except ValueError as e:
        assert "strength" in str(e)
        return
    assert bool(torch.isfinite(tau).all()) and bool(torch.isfinite(w.x).all())
    assert bool((tau.diff(dim=1) >= 0).all())
    assert bool((tau[:, 0] == 0).all()) and bool((tau[:, -1] == 1).all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_time_warp_zero_strength_is_the_identity(dtype):
    d = Demonstrations(x=_x(T=50, dtype=dtype), dt=0.1)
    w, tau = time_warp(d, 0.0, torch.Generator().manual_seed(0), return_phase=True)
    # today: τ = cumsum/total differs from linspace by an ulp, so the "unwarped" demos are not the input
    assert torch.equal(w.x, d.x)


def test_spatial_noise_dims_must_be_ints():
    d = Demonstrations(x=_x(), dt=0.1)
    # today: dims=[0.7] is silently truncated to [0] and dims=[True] is read as [1]
    with pytest.raises((TypeError, ValueError), match="dims"):
        spatial_noise(d, 0.1, torch.Generator().manual_seed(0), dims=[0.7])
    with pytest.raises((TypeError, ValueError), match="dims"):
        spatial_noise(d, 0.1, torch.Generator().manual_seed(0), dims=[True])


@pytest.mark.parametrize("scale", [torch.tensor(0.1, dtype=torch.float64), np.int64(1)],
                         ids=["tensor0d", "npint"])
def test_spatial_noise_scalar_scale_in_any_numeric_type(scale):
    d = Demonstrations(x=_x(), dt=0.1)
    ref = spatial_noise(d, float(scale), torch.Generator().manual_seed(0))
    # today: a 0-d tensor or a numpy integer is treated as a per-dim list and rejected ("2 of them")
    got = spatial_noise(d, scale, torch.Generator().manual_seed(0))
    assert torch.equal(got.x, ref.x)


@pytest.mark.parametrize("kw,name", [({"warp": math.nan}, "warp"), ({"noise": math.inf}, "noise"),
                                     ({"warp": -1.0}, "warp"), ({"noise": -0.1}, "noise"),
                                     ({"noise": "x"}, "noise")])
def test_handwriting_validates_warp_and_noise_by_name(kw, name):
    # today: NaN/inf -> TypeError "field 'meta' must be JSON-serialisable"; negative -> an error naming
    # time_warp's 'strength' / spatial_noise's 'scale'; a string -> float()'s bare ValueError
    with pytest.raises((ValueError, TypeError), match=f"handwriting.*'{name}'"):
        handwriting("S", 2, 20, generator=torch.Generator().manual_seed(0), **kw)


# ------------------------------------------------------------------------------------- cat
def test_cat_refuses_frames_of_different_dtypes():
    x = _x(N=2)
    a = Demonstrations(x=x, dt=0.1, frames={"ok": torch.tensor([True, False])})
    b = Demonstrations(x=x, dt=0.1, frames={"ok": torch.tensor([1, 0])})
    # today: silently promoted to int64 (and float32 + float64 frames to float64)
    with pytest.raises((ValueError, TypeError), match="ok"):
        Demonstrations.cat([a, b])
    c = Demonstrations(x=x, dt=0.1, frames={"g": torch.zeros(2, dtype=torch.float32)})
    e = Demonstrations(x=x, dt=0.1, frames={"g": torch.zeros(2, dtype=torch.float64)})
    with pytest.raises((ValueError, TypeError), match="g"):
        Demonstrations.cat([c, e])


# ------------------------------------------------------------------------------------- minor defects
def test_from_arrays_resample_refuses_a_user_frame_named_duration_or_length():
    xs = [np.zeros((4, 1)), np.zeros((6, 1))]
    for name in ("duration", "length"):
        # before: the user's frame silently replaced the computed one (setdefault kept the user's)
        with pytest.raises(ValueError, match=f"'{name}'"):
            Demonstrations.from_arrays(xs, dt=0.1, resample=5, frames={name: np.ones(2)})
    # without resampling nothing is computed: a frame of that name is the user's own
    d = Demonstrations.from_arrays([np.zeros((4, 1))] * 2, dt=0.1, frames={"duration": np.array([3.0, 4.0])})
    assert d.frames["duration"].tolist() == [3.0, 4.0]
    r = Demonstrations.from_arrays(xs, dt=0.1, resample=5, frames={"mine": np.ones(2)})
    assert r.frames["length"].tolist() == [4, 6]
    assert torch.allclose(r.frames["duration"], torch.tensor([0.3, 0.5], dtype=torch.float64))


def _small_pendulum(x0, T=8):
    from controllers.costs import QuadraticCost
    from controllers.ilqr import ILQRProblem
    from controllers.systems import Pendulum

    f64 = dict(dtype=torch.float64)
    cost = QuadraticCost(Q=0.1 * torch.eye(2, **f64), R=0.01 * torch.eye(1, **f64),
                         x_ref=torch.tensor([0.5, 0.0], dtype=torch.float64))
    sys = Pendulum(dt=0.05)
    return sys, cost, ILQRProblem(sys, cost, x0, T)


def test_expert_and_mpc_demos_refuse_to_override_computed_meta_and_frames():
    from learning.demos import expert_demos, mpc_demos

    x0 = torch.tensor([[0.0, 0.0], [0.2, 0.0]], dtype=torch.float64)
    sys, cost, prob = _small_pendulum(x0)
    # before: the user's meta silently replaced 'source' / 'total', a user frame 'index' the computed one
    with pytest.raises(ValueError, match="'source'"):
        expert_demos(prob, meta={"source": "mine"})
    with pytest.raises(ValueError, match="'index'"):
        expert_demos(prob, frames={"index": torch.zeros(2)})
    with pytest.raises(ValueError, match="'horizon'"):
        mpc_demos(sys, cost, x0, 4, 2, meta={"horizon": 99})
    with pytest.raises(ValueError, match="'converged'"):
        mpc_demos(sys, cost, x0, 4, 2, frames={"converged": torch.zeros(2)})
    d = expert_demos(prob, meta={"note": "kept"})
    assert d.meta["note"] == "kept" and d.meta["source"] == "expert_demos" and d.meta["total"] == 2


def test_expert_and_mpc_demos_are_detached_data_alike():
    from learning.demos import expert_demos, mpc_demos

    x0 = torch.tensor([[0.0, 0.0], [0.2, 0.0]], dtype=torch.float64)
    sys, cost, prob = _small_pendulum(x0.clone().requires_grad_(True))
    e = expert_demos(prob)
    m = mpc_demos(sys, cost, x0.clone().requires_grad_(True), 4, 3)
    # documented: both run without a graph, even when the inputs require grad
    for d in (e, m):
        assert not d.x.requires_grad and not d.u.requires_grad and d.x.grad_fn is None
    plain = expert_demos(_small_pendulum(x0)[2])
    assert torch.equal(plain.x, e.x) and torch.equal(plain.u, e.u)


def test_constructor_keeps_tensors_by_reference_as_documented():
    x = _x()
    f = torch.arange(3)
    meta = {"k": [1]}
    d = Demonstrations(x=x, dt=0.1, frames={"f": f}, meta=meta)
    assert d.x is x and d.frames["f"] is f  # no copy (documented in the class docstring)
    meta["k"].append(2)
    assert d.meta == {"k": [1]}  # meta is a deep copy
    assert "No copy" in Demonstrations.__doc__


def test_load_errors_from_validation_name_the_file(tmp_path):
    # a well-formed file whose content fails validation (a non-positive dt) names the file too
    with pytest.raises(ValueError, match=r"neg\.npz.*'dt'"):
        Demonstrations.load(_write(tmp_path / "neg.npz", dt=np.array(-0.1)))
    # a 0-d integer dt is a real number: accepted
    assert Demonstrations.load(_write(tmp_path / "int.npz", dt=np.array(2, dtype=np.int64))).dt == 2.0


def test_dt_as_a_bool_or_complex_tensor_is_refused():
    with pytest.raises(TypeError, match="'dt'"):
        Demonstrations(x=_x(), dt=torch.tensor(True))
    with pytest.raises(TypeError, match="dt"):
        Demonstrations.from_arrays([np.zeros((4, 1))] * 2, dt=torch.tensor([True, True]))
    d = Demonstrations.from_arrays([np.zeros((4, 1))] * 2, dt=torch.tensor([0.5, 0.5]))
    assert d.dt == 0.5
