"""Quadrotor references from differential flatness (NED, ṗ = v, v̇ = g e₃ − a_T R e₃, Ṙ = R [ω]×): the
derivatives and body rates against finite differences, the continuous dynamics, orthonormality, open-loop
consistency under RK4 / R Exp(ω dt) integration, the heading options and their singularities, and the
three scenarios' defining figures (circle ramp to 5 m/s, triple flip through 6π, 8 m/s loop)."""

from __future__ import annotations

import math
from functools import cache

import pytest
import torch

from controllers.systems.quadrotor_flatness import (
    FlatReference,
    circle_ramp,
    flat_reference,
    loop,
    triple_flip,
)
from torchlie import so3

# torch's first forward-mode call scripts its jvp decompositions with the deprecated torch.jit.script
pytestmark = pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning")

D64 = torch.float64
G = 9.81
E1 = torch.tensor([1.0, 0.0, 0.0], dtype=D64)
E2 = torch.tensor([0.0, 1.0, 0.0], dtype=D64)
E3 = torch.tensor([0.0, 0.0, 1.0], dtype=D64)


def _wavy(tk):
    """A generic 3-D trajectory (thrust never vanishes: |p̈_z| ≤ 1.8 < g)."""
    return torch.stack((1.5 * torch.sin(0.8 * tk), 0.7 * torch.cos(1.3 * tk) - 0.7,
                        -2.0 + 0.4 * torch.sin(2.1 * tk)))


def _yaw(tk):
    return 0.6 * torch.sin(0.5 * tk) + 0.2 * tk


def _planar(tk):
    return torch.stack((2.0 * torch.sin(1.1 * tk), torch.zeros_like(tk), -1.5 + 0.8 * torch.cos(1.7 * tk)))


#: name -> (reference at arbitrary times, a span of times to test away from the profiles' knots)
BUILDERS = {
    "yaw": (lambda t: flat_reference(_wavy, t, heading=_yaw), (0.0, 6.0)),
    "const-yaw": (lambda t: flat_reference(_wavy, t, heading=-2.5), (0.0, 6.0)),
    "pitch-axis": (lambda t: flat_reference(_wavy, t, pitch_axis=(0.3, 1.0, 0.2)), (0.0, 6.0)),
    "planar": (lambda t: flat_reference(_planar, t, pitch_axis=(0.0, 1.0, 0.0)), (0.0, 6.0)),
    "circle": (lambda t: circle_ramp(t=t), (0.1, 12.4)),
    "flip": (lambda t: triple_flip(t=t), (0.05, 5.0)),
    "loop": (lambda t: loop(t=t), (0.1, 16.0)),
}


@cache
def _scenario(name: str) -> FlatReference:
    return {"circle": circle_ramp, "flip": triple_flip, "loop": loop}[name]()


def _times(span, n=23):
    # irrational-ish spacing: never within 2 h of the smooth steps' knots of the scenarios
    return torch.linspace(span[0] + 0.0137, span[1] - 0.0213, n, dtype=D64)


def _fd(build, t, h):
    """4th-order central differences of p, v, R at ``t`` (one call on the 5-point stencil)."""
    n = t.shape[0]
    ref = build(torch.cat([t + k * h for k in (-2, -1, 0, 1, 2)]))

    def d(x):
        xm2, xm1, _, xp1, xp2 = x.split(n)
        return (xm2 - 8 * xm1 + 8 * xp1 - xp2) / (12 * h)

    centre = FlatReference(*(x.split(n)[2] for x in ref))
    return centre, d(ref.p), d(ref.v), d(ref.R)


@pytest.mark.parametrize("name", list(BUILDERS))
def test_reference_satisfies_the_continuous_dynamics(name):
    build, span = BUILDERS[name]
    ref, dp, dv, dR = _fd(build, _times(span), 1e-3)
    # ṗ = v and v̇ = a against 4th-order central differences
    torch.testing.assert_close(ref.v, dp, atol=1e-8, rtol=0)
    torch.testing.assert_close(ref.a, dv, atol=1e-7, rtol=0)
    # Rᵀ Ṙ = [ω]×, Ṙ by differences of R(t) (the vee of the skew part, and the full matrix)
    W = ref.R.transpose(-1, -2) @ dR
    torch.testing.assert_close(so3.vee(W), ref.omega, atol=1e-6, rtol=0)
    torch.testing.assert_close(W, so3.hat(ref.omega), atol=1e-6, rtol=0)
    # v̇ = g e₃ − a_T R e₃ (NED: gravity +z, thrust along the body's −z)
    torch.testing.assert_close(G * E3 - ref.thrust[:, None] * ref.R[:, :, 2], ref.a, atol=1e-10, rtol=0)
    eye = torch.eye(3, dtype=D64).expand_as(ref.R)
    torch.testing.assert_close(ref.R.transpose(-1, -2) @ ref.R, eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(ref.R), torch.ones_like(ref.t), atol=1e-12, rtol=0)
    assert bool((ref.thrust > 0).all())
    assert ref.u.shape == (len(ref.t), 4)
    assert torch.equal(ref.u[:, 0], ref.thrust) and torch.equal(ref.u[:, 1:], ref.omega)


def test_heading_conventions():
    t = torch.linspace(0.0, 6.0, 41, dtype=D64)
    ref = flat_reference(_wavy, t, heading=_yaw)
    psi = _yaw(t)
    xc = torch.stack((torch.cos(psi), torch.sin(psi), torch.zeros_like(psi)), -1)
    xb, yb = ref.R[:, :, 0], ref.R[:, :, 1]
    # y_b ⟂ x_c and x_b on x_c's side: ψ is the yaw of a Z-X-Y sequence
    torch.testing.assert_close((yb * xc).sum(-1), torch.zeros_like(t), atol=1e-13, rtol=0)
    assert bool(((xb * xc).sum(-1) > 0.5).all())
    assert torch.equal(flat_reference(_wavy, t).R, flat_reference(_wavy, t, heading=0.0).R)
    # a pitch axis in the plane of the motion's normal: y_b = c exactly, rates purely about y
    ref = flat_reference(_planar, t, pitch_axis=(0.0, 2.0, 0.0))
    torch.testing.assert_close(ref.R[:, :, 1], E2.expand(41, 3), atol=1e-15, rtol=0)
    torch.testing.assert_close(ref.omega[:, [0, 2]], torch.zeros(41, 2, dtype=D64), atol=1e-13, rtol=0)
    # hover: identity attitude, thrust g, no rates
    hover = flat_reference(lambda tk: torch.stack((0 * tk, 0 * tk, 0 * tk - 1.0)), t)
    torch.testing.assert_close(hover.R, torch.eye(3, dtype=D64).expand(41, 3, 3), atol=0, rtol=0)
    torch.testing.assert_close(hover.thrust, torch.full_like(t, G), atol=0, rtol=0)


def test_dtype_and_grid():
    ref = flat_reference(_wavy, torch.linspace(0, 1, 5, dtype=torch.float32))
    assert all(x.dtype == torch.float32 for x in ref)
    ref = triple_flip(dtype=torch.float32, t=[0.0, 1.0])
    assert all(x.dtype == torch.float32 for x in ref) and ref.t.shape == (2,)
    ref = flat_reference(_wavy, [0.0, 0.5])
    assert ref.t.dtype == D64
    ref = triple_flip(dt=0.02, pad=7)
    end = 2 * math.pi * 3 / 4.5 + 0.6
    assert ref.t.shape == (math.ceil(end / 0.02) + 1 + 7,)
    torch.testing.assert_close(ref.t[1:] - ref.t[:-1], torch.full((len(ref.t) - 1,), 0.02, dtype=D64))


def _rollout(ref: FlatReference, starts, steps=10):
    """Integrate the continuous dynamics from the reference states at ``starts`` with the reference
    inputs, linearly interpolated between samples: RK4 on (p, v), R ← R Exp(ω dt) (midpoint ω)."""
    dt = (ref.t[1] - ref.t[0]).item()
    p, v, R = ref.p[starts], ref.v[starts], ref.R[starts]

    def acc(thrust, Rm):
        return G * E3 - thrust[:, None] * Rm[:, :, 2]

    for j in range(steps):
        k = starts + j
        T0, T1 = ref.thrust[k], ref.thrust[k + 1]
        w = 0.5 * (ref.omega[k] + ref.omega[k + 1])
        Rh, R1 = R @ so3.exp(0.5 * dt * w), R @ so3.exp(dt * w)
        a1, a2, a4 = acc(T0, R), acc(0.5 * (T0 + T1), Rh), acc(T1, R1)
        p = p + dt * v + dt * dt / 6 * (a1 + 2 * a2)
        v = v + dt / 6 * (a1 + 4 * a2 + a4)
        R = R1
    k = starts + steps
    return ((p - ref.p[k]).norm(dim=-1), (v - ref.v[k]).norm(dim=-1),
            so3.log(ref.R[k].transpose(-1, -2) @ R).norm(dim=-1))


@pytest.mark.parametrize("name", ["circle", "flip", "loop"])
def test_open_loop_integration_tracks_the_reference(name):
    ref = _scenario(name)
    # every sample of the default grid: v̇ = g e₃ − a_T R e₃, R ∈ SO(3), a_T > 0
    torch.testing.assert_close(G * E3 - ref.thrust[:, None] * ref.R[:, :, 2], ref.a, atol=1e-10, rtol=0)
    eye = torch.eye(3, dtype=D64).expand_as(ref.R)
    torch.testing.assert_close(ref.R.transpose(-1, -2) @ ref.R, eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(ref.R), torch.ones_like(ref.t), atol=1e-12, rtol=0)
    assert bool((ref.thrust > 0).all())
    starts = torch.arange(0, len(ref.t) - 11, 7)
    dp, dv, dR = _rollout(ref, starts)  # 0.1 s windows at the 100 Hz grid
    assert dp.max() < 2e-4 and dv.max() < 5e-3 and dR.max() < 5e-3
    # the check has teeth: the same integration with the rates reversed drifts far away
    flipped = ref._replace(omega=-ref.omega)
    assert _rollout(flipped, starts)[0].max() > 5e-3


def test_circle_ramp():
    ref = _scenario("circle")
    pad = 50
    end = len(ref.t) - pad - 1
    assert ref.t[end].item() == pytest.approx(12.0, abs=1e-12)
    speed = ref.v.norm(dim=-1)
    # starts in exact hover at rest, reaches 5 m/s at the end of the ramp and holds it in the pad
    assert speed[0].item() == 0 and ref.a[0].norm().item() == 0
    torch.testing.assert_close(ref.R[0], torch.eye(3, dtype=D64), atol=0, rtol=0)
    torch.testing.assert_close(speed[end:], torch.full((pad + 1,), 5.0, dtype=D64), atol=1e-12, rtol=0)
    assert bool((speed[1:] >= speed[:-1] - 1e-12).all())
    # linear ramp between the blends: acceleration 5 / (12 − 1), speed a (t − ½ s)
    mid = (ref.t > 1.0) & (ref.t < 11.0)
    torch.testing.assert_close(speed[mid], 5.0 / 11.0 * (ref.t[mid] - 0.5), atol=1e-12, rtol=0)
    # the circle: radius 1.3 at constant altitude, peak horizontal acceleration v²/r
    torch.testing.assert_close(ref.p[:, :2].norm(dim=-1), torch.full_like(ref.t, 1.3), atol=1e-12, rtol=0)
    torch.testing.assert_close(ref.p[:, 2], torch.full_like(ref.t, -1.0), atol=0, rtol=0)
    assert ref.a[:, :2].norm(dim=-1).max().item() == pytest.approx(25.0 / 1.3, rel=1e-12)
    # the figures stated in the docstring
    pk = ref.peaks()
    assert pk["speed"] == pytest.approx(5.0, abs=1e-12)
    assert pk["thrust"] == pytest.approx(math.hypot(G, 25 / 1.3), rel=1e-12)
    assert pk["thrust"] == pytest.approx(21.59, abs=0.005) and pk["thrust_min"] == pytest.approx(G)
    assert pk["rate"] == pytest.approx(7.58, abs=0.005)


def test_loop():
    ref = _scenario("loop")
    end_t = 4.0 + 3 * 2 * math.pi * 5.0 / 8.0
    end = len(ref.t) - 50 - 1
    assert ref.t[end - 1].item() < end_t <= ref.t[end].item()
    held = ref.t >= 4.0
    speed = ref.v.norm(dim=-1)
    torch.testing.assert_close(speed[held], torch.full_like(speed[held], 8.0), atol=1e-12, rtol=0)
    lateral = ref.a[held, :2].norm(dim=-1)
    torch.testing.assert_close(lateral, torch.full_like(lateral, 64 / 5.0), atol=1e-10, rtol=0)
    assert 64 / 5.0 <= 1.5 * G
    # more than three laps flown: the angle swept (unwrapped) exceeds 6π
    ang = torch.atan2(ref.p[:, 1], ref.p[:, 0])
    swept = torch.remainder(ang[1:] - ang[:-1] + math.pi, 2 * math.pi) - math.pi
    assert swept.sum().item() > 6 * math.pi
    pk = ref.peaks()
    assert pk["speed"] == pytest.approx(8.0, abs=1e-12)
    assert pk["thrust"] == pytest.approx(math.hypot(G, 12.8), rel=1e-12)
    assert pk["thrust"] == pytest.approx(16.13, abs=0.005) and pk["rate"] == pytest.approx(2.09, abs=0.005)


def test_triple_flip():
    ref = _scenario("flip")
    speed, r = 4.5, 1.0
    omega_loop = speed / r
    pk = ref.peaks()
    # limits: thrust within (0, 4 g], body rates ≤ 15 rad/s; the figures stated in the docstring
    assert 0 < pk["thrust_min"] and pk["thrust"] <= 4 * G and pk["rate"] <= 15
    assert pk["speed"] == pytest.approx(4.5, abs=1e-12) and pk["thrust"] == pytest.approx(30.06, abs=0.005)
    assert pk["rate"] == pytest.approx(8.73, abs=0.005)
    # three full nose-up turns about the body y axis: by the rates, and by the thrust axis' winding
    zeros = torch.zeros(len(ref.t), 2, dtype=D64)
    torch.testing.assert_close(ref.omega[:, [0, 2]], zeros, atol=1e-12, rtol=0)
    wy, zb_x = ref.omega[:, 1], ref.R[:, 0, 2]
    # nose down to speed up (body z tilted back), nose up to slow down; pitching nose-up throughout the
    # loops at full speed
    assert zb_x[(ref.t > 0) & (ref.t < 0.1)].max() < 0 and zb_x[(ref.t > 4.7) & (ref.t < 4.78)].min() > 0
    assert bool((wy[(ref.t >= 0.6) & (ref.t <= 2 * math.pi * 3 / 4.5)] > 0).all())
    assert (0.5 * (wy[1:] + wy[:-1]) * 0.01).sum().item() == pytest.approx(6 * math.pi, abs=1e-4)
    zb = ref.R[:, :, 2]
    ang = torch.atan2(zb[:, 0], zb[:, 2])  # pitch angle θ: z_b = (sin θ, 0, cos θ)
    turn = torch.remainder(ang[1:] - ang[:-1] + math.pi, 2 * math.pi) - math.pi
    assert turn.sum().item() == pytest.approx(6 * math.pi, abs=1e-9)
    # upside down at the exact tops (φ = π, 3π, 5π at full speed, t = φ/Ω + T/2): body z up (R e₃ = −e₃),
    # thrust v²/r − g, pitch rate Ω κ/(κ − 1) with κ = v²/(g r)
    tops = triple_flip(t=[(2 * k + 1) * math.pi / omega_loop + 0.3 for k in range(3)])
    torch.testing.assert_close(tops.R[:, :, 2], -E3.expand(3, 3), atol=1e-12, rtol=0)
    torch.testing.assert_close(tops.p[:, 2], torch.full((3,), -4.0, dtype=D64), atol=1e-12, rtol=0)
    kappa = speed ** 2 / (G * r)
    expected = torch.tensor([speed ** 2 / r - G, omega_loop * kappa / (kappa - 1)], dtype=D64).expand(3, 2)
    torch.testing.assert_close(torch.stack((tops.thrust, tops.omega[:, 1]), -1), expected, atol=1e-10, rtol=0)
    # from hover to hover at the same point; the pad holds it
    for k in (0, -51, -1):
        torch.testing.assert_close(ref.p[k], torch.tensor([0.0, 0.0, -2.0], dtype=D64), atol=1e-12, rtol=0)
        torch.testing.assert_close(ref.v[k], torch.zeros(3, dtype=D64), atol=1e-12, rtol=0)
        torch.testing.assert_close(ref.R[k], torch.eye(3, dtype=D64), atol=1e-12, rtol=0)
        torch.testing.assert_close(ref.u[k], torch.tensor([G, 0, 0, 0], dtype=D64), atol=1e-12, rtol=0)


def test_triple_flip_is_smooth_across_the_profile_knots():
    # where the speed-up and slow-down start and stop, acceleration, body rates (hence jerk) and snap are
    # continuous (snap by one-sided 2nd-order differences of a on each side)
    t2 = 2 * math.pi * 3 / 4.5
    knots = torch.tensor([0.6, t2, t2 + 0.6], dtype=D64)
    eps, d = 1e-9, 1e-4
    offsets = [-eps - k * d for k in range(4)] + [eps + k * d for k in range(4)]
    ref = triple_flip(t=torch.cat([knots + o for o in offsets]))
    a = ref.a.reshape(8, 3, 3)
    w = ref.omega.reshape(8, 3, 3)
    torch.testing.assert_close(a[0], a[4], atol=1e-6, rtol=0)
    torch.testing.assert_close(w[0], w[4], atol=1e-6, rtol=0)
    snap_lo = (2 * a[0] - 5 * a[1] + 4 * a[2] - a[3]) / d ** 2
    snap_hi = (2 * a[4] - 5 * a[5] + 4 * a[6] - a[7]) / d ** 2
    torch.testing.assert_close(snap_lo, snap_hi, atol=0.5, rtol=0)
    assert snap_lo.abs().max() > 10  # not trivially equal: the snap is large at the knots


def test_singular_constructions_raise():
    t = torch.tensor([0.0, 0.5, 1.0, 1.5], dtype=D64)

    # free fall at t = 1 only: a_z = g + 12 (t − 1)²
    def falling(tk):
        return torch.stack((0 * tk, 0 * tk, 0.5 * G * tk ** 2 + (tk - 1.0) ** 4))

    with pytest.raises(ValueError, match=r"'position'.*time index 2 .*free fall"):
        flat_reference(falling, t)
    # thrust axis horizontal along +x: a = g e₃ − 3 e₁
    sideways = lambda tk: 0.5 * tk ** 2 * (G * E3 - 3.0 * E1)
    with pytest.raises(ValueError, match=r"'heading'.*time index 2 "):
        flat_reference(sideways, t, heading=lambda tk: tk - 1.0)  # ψ = 0 (x_c = z_b) at t = 1
    with pytest.raises(ValueError, match=r"'heading'.*time index 0 "):
        flat_reference(sideways, t)
    with pytest.raises(ValueError, match=r"'pitch_axis'.*time index 0 "):
        flat_reference(sideways, t, pitch_axis=(-2.0, 0.0, 0.0))
    ok = flat_reference(sideways, t, pitch_axis=(0.0, 1.0, 0.0))  # z_b = e₁ ⟂ c: regular
    torch.testing.assert_close(ok.R[:, :, 2], E1.expand(4, 3), atol=1e-15, rtol=0)
    with pytest.raises(ValueError, match=r"'pitch_axis'.*nonzero"):
        flat_reference(_wavy, t, pitch_axis=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match=r"either argument 'heading'.*'pitch_axis'"):
        flat_reference(_wavy, t, heading=0.0, pitch_axis=(0.0, 1.0, 0.0))
    with pytest.raises(ValueError, match=r"'speed'.*speed²/radius > g"):
        triple_flip(speed=3.0)
    with pytest.raises(ValueError, match=r"'duration' must exceed"):
        circle_ramp(duration=0.5)
