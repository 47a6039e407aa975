"""The pixel coverage gate and EWA projection: gradients against the supplement's eq. 17-20 and finite differences."""

import math

import pytest
import torch

from proxycodec.camera import Camera
from proxycodec.render.project import (
    GATE_DET_FLOOR, GateConfig, coverage_gate, covariance_3d, project_gaussians, quat_to_rotmat,
)

GATE = GateConfig()


@pytest.fixture(autouse=True)
def float64_default():
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(old)


def gated_alpha(alpha, sigma, gate=GATE):
    a, b, c = sigma[0, 0], 0.5 * (sigma[0, 1] + sigma[1, 0]), sigma[1, 1]
    return alpha * coverage_gate(a * c - b * b, gate)


@pytest.mark.parametrize("sigma", [[[0.5, 0.1], [0.1, 0.3]], [[0.02, 0.0], [0.0, 0.05]], [[4.0, -1.0], [-1.0, 2.0]]])
def test_gate_gradients_match_supplement_eq_17_to_20(sigma):
    sigma = torch.tensor(sigma, requires_grad=True)
    alpha = torch.tensor(0.7, requires_grad=True)
    upstream = 1.3  # dL/d alpha_tilde
    (upstream * gated_alpha(alpha, sigma)).backward()
    with torch.no_grad():
        det = torch.det(sigma)
        A = math.pi * torch.sqrt(det + GATE_DET_FLOOR)
        g = torch.sigmoid(GATE.kappa * (A - GATE.eta))
        eq17 = upstream * g
        # eq. 20 with the floor made explicit: sqrt(det) -> det / sqrt(det + floor) (equal when det >> floor)
        eq20 = upstream * alpha * GATE.kappa * g * (1 - g) * (math.pi / 2) * det / torch.sqrt(det + GATE_DET_FLOOR) \
            * torch.linalg.inv(sigma).T
        eq20_paper = upstream * alpha * GATE.kappa * g * (1 - g) * (math.pi / 2) * torch.sqrt(det) * torch.linalg.inv(sigma).T
    # Sigma is symmetric: autograd's gradient of the symmetrised entry splits the off-diagonal term evenly.
    assert torch.allclose(alpha.grad, eq17, rtol=1e-12)
    assert torch.allclose(sigma.grad, eq20, rtol=1e-9, atol=1e-12)
    rel_floor = GATE_DET_FLOOR / (2 * float(det))
    assert torch.allclose(sigma.grad, eq20_paper, rtol=2 * rel_floor + 1e-9)


def test_gate_gradient_matches_finite_differences():
    sigma = torch.tensor([[0.3, 0.05], [0.05, 0.2]], requires_grad=True)
    alpha = torch.tensor(0.4, requires_grad=True)
    assert torch.autograd.gradcheck(lambda s, a: gated_alpha(a, s), (sigma, alpha), eps=1e-6, atol=1e-8)


def test_gate_limits_and_disabled():
    det = torch.tensor([0.0, 1e-12, 1.0, 1e6])
    g = coverage_gate(det, GATE)
    assert torch.all((g > 0) & (g <= 1))
    assert g[0] == pytest.approx(1 / (1 + math.exp(GATE.kappa * GATE.eta - GATE.kappa * math.pi * 0.01)), rel=1e-9)
    assert g[-1] == pytest.approx(1.0)
    assert torch.all(coverage_gate(det, GateConfig(enabled=False)) == 1)


def test_gate_gradient_bounded_for_singular_covariance():
    # det Sigma2D = 0 exactly (rank one) and anisotropy 1e6: the gradient stays finite and bounded.
    for s in ([[1.0, 1.0], [1.0, 1.0]], [[1e3, 0.0], [0.0, 1e-3]], [[1e-9, 0.0], [0.0, 1e-9]]):
        sigma = torch.tensor(s, requires_grad=True)
        gated_alpha(torch.tensor(1.0), sigma).backward()
        assert torch.isfinite(sigma.grad).all()
        assert sigma.grad.abs().max() < 1e6


def test_quaternion_zero_and_tiny_norm():
    q = torch.tensor([[0.0, 0.0, 0.0, 0.0], [1e-30, 0, 0, 0], [2.0, 0, 0, 0], [0.0, 1.0, 0.0, 0.0]], requires_grad=True)
    R = quat_to_rotmat(q)
    assert torch.isfinite(R).all()
    assert torch.allclose(R[0], torch.eye(3)) and torch.allclose(R[2], torch.eye(3), atol=1e-8)
    assert torch.allclose(R[3], torch.diag(torch.tensor([1.0, -1.0, -1.0])), atol=1e-8)
    R.sum().backward()
    assert torch.isfinite(q.grad).all() and q.grad.abs().max() < 1e5


def test_projection_matches_a_hand_computation():
    cam = Camera(torch.eye(4).numpy(), 100.0, 80.0, 32.0, 24.0, 64, 48)
    means = torch.tensor([[0.1, -0.05, 2.0]])
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]])
    scales = torch.tensor([[0.05, 0.02, 0.01]])
    p = project_gaussians(means, quats, scales, torch.tensor([0.9]), torch.ones(1, 3), cam)
    assert p.count == 1
    assert torch.allclose(p.means2d[0], torch.tensor([100 * 0.05 + 32, 80 * -0.025 + 24]))
    J = torch.tensor([[100 / 2.0, 0, -100 * 0.1 / 4.0], [0, 80 / 2.0, 80 * 0.05 / 4.0]])
    cov2 = J @ torch.diag(scales[0] ** 2) @ J.T
    g = torch.sigmoid(4 * (math.pi * torch.sqrt(torch.det(cov2) + GATE_DET_FLOOR) - 0.25))
    assert torch.allclose(p.opacities[0], 0.9 * g)
    cov2d = cov2 + 0.3 * torch.eye(2)
    inv = torch.linalg.inv(cov2d)
    assert torch.allclose(p.conics[0], torch.stack([inv[0, 0], inv[0, 1], inv[1, 1]]))


def test_culling_drops_what_no_pixel_can_see():
    cam = Camera.look_at([0, -3, 0], [0, 0, 0], width=40, height=30)
    means = torch.tensor([[0.0, 0.0, 0.0], [0.0, -4.0, 0.0], [50.0, 0.0, 0.0], [0.0, 0.0, 0.1]])
    p = project_gaussians(means, torch.tensor([[1.0, 0, 0, 0]] * 4), torch.full((4, 3), 0.05),
                          torch.tensor([0.9, 0.9, 0.9, 0.001]), torch.ones(4, 3), cam)
    assert p.index.tolist() == [0]  # behind the camera, off-screen and invisible opacity are culled


def test_covariance_is_psd_for_extreme_scales():
    q = torch.randn(64, 4)
    s = torch.exp(torch.empty(64, 3).uniform_(-20, 10))
    cov = covariance_3d(q, s)
    ev = torch.linalg.eigvalsh(cov)
    assert torch.isfinite(cov).all() and (ev > -1e-6 * ev.abs().amax(1, keepdim=True)).all()


@pytest.mark.parametrize("backend", ["reference", "cpu"])
@pytest.mark.parametrize("sigma_px", [0.25, 0.5, 2.0])
def test_antialiased_keeps_a_gaussians_integral(sigma_px, backend):
    """gsplat's antialiased mode: the 0.3-px^2 dilation no longer adds to what a Gaussian deposits. One isotropic
    Gaussian of sigma px in the middle of a black image (gate off): its dilated footprint summed over the pixel
    centres is o 2 pi sigma^2 with the compensation, o 2 pi (sigma^2 + 0.3) without; the rasterizer draws exactly that
    footprint where alpha >= 1/255."""
    from proxycodec.render import render_gaussians

    W = 64
    cam = Camera.look_at([0, -4, 0], [0, 0, 0], fov_x_deg=40.0, width=W, height=W)
    s = sigma_px * 4.0 / cam.fx  # a world scale projecting to sigma_px pixels at the centre, 4 units away
    args = (torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), s), torch.tensor([0.9]),
            torch.ones(1, 3))
    ys, xs = torch.meshgrid(torch.arange(W) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    for aa, area in ((False, sigma_px ** 2 + 0.3), (True, math.sqrt(sigma_px ** 4 + GATE_DET_FLOOR))):
        gate = GateConfig(enabled=False, antialiased=aa)
        p = project_gaussians(*args, cam, gate=gate)
        (ca, cb, cc), (mx, my) = p.conics[0], p.means2d[0]
        dx, dy = xs - mx, ys - my
        alpha = p.opacities[0] * torch.exp(-0.5 * (ca * dx * dx + 2 * cb * dx * dy + cc * dy * dy))
        assert alpha.sum().item() == pytest.approx(0.9 * 2 * math.pi * area, rel=0.01)
        r = render_gaussians(*args, cam, background=(0.0, 0.0, 0.0), gate=gate, backend=backend)
        drawn = torch.where(alpha >= 1 / 255, alpha, 0.0)
        assert torch.allclose(r.alpha.double().reshape(W, W), drawn, atol=1e-6)


def test_antialiased_compensation_with_the_gate_and_its_json():
    """rho multiplies the gated opacity; ``Projected.gate`` reports the product; the flag survives its JSON, which
    scenes without it do not carry (their bytes stay as they were)."""
    cam = Camera.look_at([0, -3, 0], [0, 0, 0], width=40, height=30)
    args = (torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.05]]), torch.tensor([[1.0, 0, 0, 0]] * 2),
            torch.tensor([[0.004] * 3, [0.2] * 3]), torch.tensor([0.9, 0.6]), torch.ones(2, 3))
    plain = project_gaussians(*args, cam)
    aa = project_gaussians(*args, cam, gate=GateConfig(antialiased=True))
    assert plain.index.tolist() == aa.index.tolist() == [0, 1]
    con = plain.conics
    det_d = 1.0 / (con[:, 0] * con[:, 2] - con[:, 1] ** 2)  # det of the dilated covariance
    a_d, c_d = con[:, 2] * det_d, con[:, 0] * det_d
    b = -con[:, 1] * det_d
    det_u = (a_d - 0.3) * (c_d - 0.3) - b * b
    rho = torch.sqrt(det_u + GATE_DET_FLOOR) / torch.sqrt(det_d)
    assert torch.allclose(aa.opacities, plain.opacities * rho, rtol=1e-10)
    assert torch.allclose(aa.gate, plain.gate * rho, rtol=1e-10)
    assert rho[0] < 0.2 < 0.9 < rho[1] < 1.0  # the sub-pixel one loses most, the larger one little
    on = GateConfig(antialiased=True)
    assert GateConfig.from_json(on.to_json()) == on
    assert "antialiased" not in GATE.to_json() and GateConfig.from_json(GATE.to_json()) == GATE
