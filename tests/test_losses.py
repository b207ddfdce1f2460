"""Eq. 4 / Eq. 5 losses: the BCE from logits stays finite and correct at the extremes."""

import math

import pytest
import torch
import torch.nn.functional as F

from srfpipe.srf import losses


def test_semantic_loss_matches_the_paper_definition_for_moderate_logits():
    logits = torch.tensor([[2.0, -1.0, 0.5], [0.0, 3.0, -2.0]])
    labels = torch.tensor([[1.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    p = torch.sigmoid(logits)
    expected = -(labels * p.log() + (1 - labels) * (1 - p).log()).sum(-1).mean()
    assert math.isclose(float(losses.semantic_loss(logits, labels)), float(expected), rel_tol=1e-6)


@pytest.mark.parametrize("value", [1e4, -1e4])
def test_huge_logits_give_finite_loss_and_gradient(value):
    logits = torch.full((5, 3), value, requires_grad=True)
    for labels in (torch.zeros(5, 3), torch.ones(5, 3)):  # all-negative and all-positive labels
        loss = losses.semantic_loss(logits, labels)
        loss.backward()
        assert torch.isfinite(loss) and torch.isfinite(logits.grad).all()
        wrong = (value > 0) != bool(labels[0, 0])
        # confidently wrong costs ~|logit| per class, confidently right costs ~0
        assert math.isclose(float(loss.detach()), 3 * 1e4 if wrong else 0.0, rel_tol=1e-4, abs_tol=1e-4)
        logits.grad = None


def test_class_without_positive_pixels_still_trains_towards_negative():
    logits = torch.zeros(8, 3, requires_grad=True)
    labels = torch.zeros(8, 3)
    labels[:, 0] = 1.0  # class 2 never appears
    losses.semantic_loss(logits, labels).backward()
    assert (logits.grad[:, 2] > 0).all()  # gradient descent lowers the logit of the absent class
    assert torch.isfinite(logits.grad).all()


def test_rays_without_labels_are_excluded_and_an_empty_selection_is_zero():
    logits = torch.randn(4, 2, requires_grad=True)
    labels = torch.randint(0, 2, (4, 2)).float()
    valid = torch.tensor([True, False, True, False])
    loss = losses.semantic_loss(logits, labels, valid)
    ref = F.binary_cross_entropy_with_logits(logits[valid], labels[valid], reduction="none").sum(-1).mean()
    assert torch.allclose(loss, ref)
    none = losses.semantic_loss(logits, labels, torch.zeros(4, dtype=torch.bool))
    none.backward()
    assert float(none) == 0.0 and torch.equal(logits.grad, torch.zeros_like(logits))


def test_total_loss_is_photometric_plus_lambda_semantic():
    rgb, target = torch.rand(6, 3), torch.rand(6, 3)
    logits, labels = torch.randn(6, 3), torch.randint(0, 2, (6, 3)).float()
    parts = losses.total_loss(rgb, target, logits, labels, lambda_sem=0.25)
    assert torch.allclose(parts["photometric"], ((rgb - target) ** 2).sum(-1).mean())
    assert torch.allclose(parts["loss"], parts["photometric"] + 0.25 * parts["semantic"])


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_losses_under_cpu_autocast_are_float32_and_finite(dtype):
    layer = torch.nn.Linear(3, 3)
    with torch.autocast("cpu", dtype=dtype):
        logits = layer(torch.randn(16, 3)) * 1e3
        loss = losses.semantic_loss(logits, torch.randint(0, 2, (16, 3)).float())
    loss.backward()
    assert loss.dtype == torch.float32 and torch.isfinite(loss)
    assert torch.isfinite(layer.weight.grad).all()
