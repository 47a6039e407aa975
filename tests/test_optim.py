"""The optimiser: the foreach step against the per-tensor loop, and both against torch's Adam."""

import numpy as np
import pytest
import torch

from proxycodec.optim import Adam


def _params(seed: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    shapes = {"features": (50, 32), "offsets": (50, 10, 3), "scalings": (50, 6), "decoder.w": (16, 68),
              "decoder.b": (16,), "frozen": (7,)}
    return {k: torch.randn(s, generator=g).requires_grad_(True) for k, s in shapes.items()}


def _grads(params: dict[str, torch.Tensor], seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    for k, p in params.items():
        # "frozen" never has a gradient; "decoder.b" gets none every third step
        p.grad = None if k == "frozen" or (k == "decoder.b" and seed % 3 == 0) else \
            torch.randn(p.shape, generator=g) * 10.0 ** float(torch.randint(-6, 2, (), generator=g))


def test_foreach_step_is_bitwise_the_per_tensor_loop():
    a, b = _params(0), _params(0)
    opt_a, opt_b = Adam(a), Adam(b)
    for it in range(12):
        if it == 5:  # a parameter that joins late keeps its own step count (bias correction)
            for params, opt in ((a, opt_a), (b, opt_b)):
                params["late"] = torch.ones(9, requires_grad=True)
                opt.add("late", params["late"])
        lrs = {"features": 5e-3, "offsets": 1e-2 * 0.9**it, "scalings": 7e-3, "decoder.w": 4e-3,
               "decoder.b": 0.0 if it == 4 else 2e-3, "late": 1e-2}
        _grads(a, it)
        _grads(b, it)
        opt_a.step(lrs)
        opt_b.step_reference(lrs)
    for k in a:
        assert torch.equal(a[k], b[k]), k
        assert torch.equal(opt_a.m[k], opt_b.m[k]) and torch.equal(opt_a.v[k], opt_b.v[k]), k
    assert opt_a.step_count == opt_b.step_count
    assert opt_a.step_count["frozen"] == 0 and opt_a.step_count["late"] == 7
    assert opt_a.step_count["decoder.b"] == 12 - 4 - 1  # 4 steps without a gradient, 1 at learning rate 0
    assert not torch.equal(a["features"], _params(0)["features"])  # it moved


@pytest.mark.parametrize("lr", [1e-3, 0.5])
def test_matches_torch_adam(lr):
    p = _params(1)
    q = {k: v.detach().clone().requires_grad_(True) for k, v in p.items()}
    ours = Adam(p, eps=1e-8)
    ref = torch.optim.Adam(list(q.values()), lr=lr, betas=(0.9, 0.999), eps=1e-8)
    for it in range(1, 9):
        _grads(p, it)
        for k, t in q.items():
            t.grad = None if p[k].grad is None else p[k].grad.clone()
        ours.step(lr)
        ref.step()
    for k in p:  # float32 rounding in another order: a few ulps of values that moved by up to 8 * lr
        np.testing.assert_allclose(p[k].detach().numpy(), q[k].detach().numpy(), rtol=2e-6, atol=1e-6, err_msg=k)
        assert not torch.equal(p[k], _params(1)[k]) or k == "frozen"


def test_step_dispatches_the_same_operations_for_any_number_of_tensors():
    """The foreach step's operation count (each a kernel launch on a GPU) does not grow with the tensors stepped."""
    from proxycodec.bench.ops import dispatch_counter

    counts = []
    for k in (2, 12):
        params = {f"p{i}": torch.randn(5, 3, requires_grad=True) for i in range(k)}
        opt = Adam(params)
        for p in params.values():
            p.grad = torch.ones_like(p)
        with dispatch_counter() as c:
            opt.step(1e-3)
        counts.append(sum(c.counts.values()))
    assert counts[0] == counts[1] <= 10, counts
