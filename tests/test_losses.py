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


@pytest.mark.parametrize("weight", [1.0, 2.0, 4.0])
def test_positive_weight_moves_the_optimum_of_a_soft_target_to_w_y_over_w_y_plus_1_minus_y(weight):
    # a mask's probability y (a blurred rim, a pixel half covered): the head settles where the
    # weighted BCE is flat, so a class whose masks say y >= 1 / (1 + w) is labelled (p >= 0.5)
    y = torch.tensor([[0.1, 0.25, 1.0 / (1.0 + weight), 0.5, 0.9]])
    optimum = weight * y / (weight * y + 1 - y)
    logits = torch.log(optimum / (1 - optimum)).requires_grad_(True)
    losses.semantic_loss(logits, y, positive_weight=weight).backward()
    assert logits.grad.abs().max() < 1e-6
    assert math.isclose(float(optimum[0, 2]), 0.5, rel_tol=1e-6)


@pytest.mark.parametrize("value", [1e4, -1e4])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16, torch.float16])
def test_soft_targets_and_positive_weight_stay_finite_for_saturated_logits(value, dtype):
    logits = torch.full((4, 3), value).to(dtype).requires_grad_(True)
    targets = torch.tensor([0.0, 0.3, 1.0]).expand(4, 3)
    loss = losses.semantic_loss(logits, targets, positive_weight=2.0)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(logits.grad.float()).all()
    # a saturated logit costs ~|logit| per unit of the target it contradicts, weighted 2 on the positive side
    contradicted = (2.0 * (1.0 + 0.3) if value < 0 else (1.0 + 0.7)) * abs(float(logits[0, 0]))
    assert math.isclose(float(loss.detach()), contradicted, rel_tol=1e-3)


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


def test_total_variation_at_random_cells_estimates_the_exact_value_and_flattens_a_floater():
    """The per-step TV is estimated at random cells; it must agree with the exact mean on a
    smooth grid and, minimised, remove an isolated spike (a floater) but keep a large blob."""
    from srfpipe.srf.losses import total_variation

    res = (24, 28, 32)
    x, y, z = torch.meshgrid(*(torch.linspace(0, 1, r) for r in res), indexing="ij")
    table = torch.stack([torch.sin(3 * x) * y, z * z], dim=-1).reshape(-1, 2)
    exact = float(total_variation(table, res))
    estimates = [float(total_variation(table, res, 4000, torch.Generator().manual_seed(s))) for s in range(8)]
    assert abs(sum(estimates) / len(estimates) - exact) < 0.1 * exact
    # every cell asked for: exact
    assert float(total_variation(table, res, 10**9)) == exact

    grid = torch.zeros(res)
    grid[4:20, 4:24, 4:28] = 5.0  # an object
    grid[2, 25, 29] = 5.0  # a floater: one cell
    values = grid.reshape(-1, 1).clone().requires_grad_(True)
    optimizer = torch.optim.SGD([values], lr=50.0)
    for step in range(60):
        optimizer.zero_grad()
        total_variation(values, res, 4096, torch.Generator().manual_seed(step)).backward()
        optimizer.step()
    after = values.detach().reshape(res)
    assert float(after[2, 25, 29]) < 1.0 < 4.0 < float(after[12, 14, 16])


def test_background_opacity_spares_the_parts_the_masks_missed():
    """On an empty backdrop only rays whose pixel shows the backdrop's colour are emptied: a stem
    the masks missed (no class, but green) keeps its opacity, and so does a masked pixel as dark
    as the backdrop; frames without masks count by their colour alone."""
    colour = torch.tensor([15.0, 14.0, 14.0]) / 255
    rgb = torch.tensor([[16.0, 14.0, 20.0],   # backdrop, no class: emptied
                        [60.0, 120.0, 40.0],  # a part the masks missed: kept
                        [14.0, 14.0, 14.0],   # masked, as dark as the backdrop: kept
                        [15.0, 15.0, 15.0]]) / 255  # backdrop in a frame without masks: emptied
    labels = torch.tensor([[0.0], [0.0], [1.0], [0.0]])
    accumulation = torch.tensor([0.2, 0.9, 0.7, 0.4])
    backdrop = losses.shows_backdrop(rgb, colour, 12.0)
    assert backdrop.tolist() == [True, False, True, True]
    valid = torch.tensor([True, True, True, False])
    assert float(losses.background_opacity_loss(accumulation, labels, valid, backdrop)) == pytest.approx(0.3)
    # without the backdrop's colour: every unmasked pixel of a labelled frame, the stem included
    assert float(losses.background_opacity_loss(accumulation, labels, valid)) == pytest.approx(0.55)


# a ray that passes above the model box: it gathers its opacity in the contracted shell alone
ABOVE_THE_BOX = torch.tensor([[0.0, 0.0, 3.0]]), torch.tensor([[0.0, 1.0, 0.0]])


def test_background_opacity_loss_empties_the_rays_that_show_no_class():
    """Rays whose pixel shows none of the classes lose the opacity they gather, in the box and
    in the contracted shell beyond it alike; the rays that show a class are not asked anything."""
    from test_stability import rays, tiny_model

    model = tiny_model(classes=1)
    model.train()
    origins, directions = rays(64)
    labels = torch.zeros(64, 1)
    labels[:32] = 1.0  # half the rays show the class
    shell_labels = torch.zeros(1, 1)
    first = float(losses.background_opacity_loss(model(origins, directions)["accumulation"], labels))
    first_shell = float(losses.background_opacity_loss(model(*ABOVE_THE_BOX)["accumulation"], shell_labels))
    assert first > 0.05 and first_shell > 0.05
    optimizer = torch.optim.Adam(model.parameters(), lr=0.05)
    for _ in range(150):  # the tiny field starts opaque along its whole rays (the shell too)
        loss = (losses.background_opacity_loss(model(origins, directions)["accumulation"], labels)
                + losses.background_opacity_loss(model(*ABOVE_THE_BOX)["accumulation"], shell_labels))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    out = model(origins, directions)
    assert float(losses.background_opacity_loss(out["accumulation"], labels)) < 0.1 * first
    assert float(losses.background_opacity_loss(model(*ABOVE_THE_BOX)["accumulation"], shell_labels)) < 0.1 * first_shell
    # no ray without a class: zero, with a graph
    none = losses.background_opacity_loss(out["accumulation"], torch.ones(64, 1))
    assert float(none) == 0.0 and none.requires_grad


def test_the_trainer_asks_the_shell_beyond_the_box_to_be_empty_too():
    """The training step's background-opacity term reads the whole ray: a backdrop ray that
    crosses only the contracted shell is charged for its opacity (a box-only term charged it 0,
    and the fog settled there, beside a plant in a tight box)."""
    from test_stability import tiny_model

    from srfpipe.settings import TrainSettings
    from srfpipe.srf.trainer import loss_terms

    model = tiny_model(classes=1)
    model.train()
    outputs = model(*ABOVE_THE_BOX)
    assert float(outputs["accumulation"][0]) > 0.05
    settings = TrainSettings.from_options({"background_opacity": 1.0})
    terms = loss_terms(settings, model, outputs, torch.zeros(1, 3), torch.zeros(1, 1), None, None)
    assert float(terms["background_opacity"]) == pytest.approx(float(outputs["accumulation"][0]))
