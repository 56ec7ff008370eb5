"""Per-image appearance codes (nerfexp.nerf.appearance): the embedding, the fields that take its codes, the
test-time fit of one code, and the paper's model left as it was without them."""

import functools

import pytest
import torch
from hydra.utils import instantiate
from omegaconf import open_dict
from torch import nn

from nerfexp.nerf.appearance import AppearanceEmbedding, CodeFit, left_columns
from nerfexp.nerf.encodings import PositionalEncoding
from nerfexp.nerf.fields import MLPViewDependence, NeRFField
from nerfexp.nerf.hierarchy import HierarchyChoice
from nerfexp.nerf.volume_renderer import VolumeRenderer
from tests.helpers import tiny_config


def test_codes_are_sized_by_the_views_and_a_step_reaches_only_the_batchs_views():
    embedding = AppearanceEmbedding(dim=4)
    assert embedding.codes.shape == (0, 4)  # no rows until the data says how many views
    embedding.set_views(5)
    views = torch.tensor([1, 3, 3])
    codes = embedding(views)
    assert codes.shape == (3, 4)
    (codes * torch.arange(1.0, 5.0)).sum().backward()
    grad = embedding.codes.grad
    assert torch.equal(grad[[0, 2, 4]], torch.zeros(3, 4))  # images not in the batch: no gradient
    assert torch.equal(grad[1], torch.arange(1.0, 5.0))  # one ray of view 1
    assert torch.equal(grad[3], 2 * torch.arange(1.0, 5.0))  # two rays of view 3: summed
    embedding.set_views(5)  # the same number again: nothing changes
    with pytest.raises(ValueError, match="3 training views"):
        embedding.set_views(3)


def test_a_checkpoints_codes_size_an_unsized_embedding_and_the_test_code_is_their_mean_or_zero():
    trained = AppearanceEmbedding(dim=2)
    trained.set_views(3)
    with torch.no_grad():
        trained.codes.copy_(torch.tensor([[1.0, 2.0], [3.0, 4.0], [5.0, 9.0]]))
    loaded = AppearanceEmbedding(dim=2)
    loaded.load_state_dict(trained.state_dict())
    assert torch.equal(loaded.codes, trained.codes)
    assert torch.equal(loaded.test_code(), torch.tensor([3.0, 5.0]))  # (1 + 3 + 5) / 3, (2 + 4 + 9) / 3
    zero = AppearanceEmbedding(dim=2, test_code="zero")
    zero.load_state_dict(trained.state_dict())
    assert torch.equal(zero.test_code(), torch.zeros(2))


def test_a_field_with_codes_feeds_them_to_the_colour_head_only():
    torch.manual_seed(0)
    head = functools.partial(MLPViewDependence, direction_encoding=PositionalEncoding(2))
    field = NeRFField(PositionalEncoding(3), head, depth=2, width=8, skips=(), appearance_dim=5)
    assert field.view_head.feature.in_features == 8 + 5
    points, dirs = torch.randn(6, 3), nn.functional.normalize(torch.randn(6, 3), dim=-1)
    a, b = field(points, dirs, torch.zeros(6, 5)), field(points, dirs, torch.ones(6, 5))
    assert torch.equal(a.sigma, b.sigma)  # the density never sees the code
    assert not torch.allclose(a.rgb, b.rgb)
    with pytest.raises(ValueError, match="no appearance codes given"):
        field(points, dirs)


def test_the_fit_steps_the_code_alone_and_finds_it():
    """A frozen linear 'renderer' W code = pixel colours: the fit must recover the code that made the target
    (least squares has one answer, W having full column rank) and leave W, and its gradient, untouched."""
    torch.manual_seed(0)
    W = nn.Linear(3, 40, bias=False)
    before = W.weight.detach().clone()
    truth = torch.tensor([0.5, -1.0, 2.0])
    target = W(truth).detach()

    def loss(pixels, code):
        return ((W(code)[pixels] - target[pixels]) ** 2).mean()
    code = CodeFit(steps=400, lr=0.05, rays=16)(loss, torch.zeros(3), 40, seed=0)
    assert torch.allclose(code, truth, atol=1e-2)
    assert torch.equal(W.weight, before) and W.weight.grad is None
    again = CodeFit(steps=400, lr=0.05, rays=16)(loss, torch.zeros(3), 40, seed=0)
    assert torch.equal(code, again)  # seeded: the same pixels, the same code
    done = []
    watched = CodeFit(steps=400, lr=0.05, rays=16)(loss, torch.zeros(3), 40, seed=0, progress=done.append)
    assert done == list(range(1, 401)) and torch.equal(watched, code)  # each step told, the fit unchanged


@pytest.mark.parametrize("width, left", [(24, 12), (25, 12), (1, 0)])
def test_the_left_half_is_fitted_and_the_right_half_with_an_odd_middle_column_scored(width, left):
    assert left_columns(width) == left


@pytest.mark.parametrize("variant", [[], ["acceleration=occupancy"], ["hierarchical=proposal"]])
def test_appearance_none_leaves_the_papers_model_bit_identical(variant):
    """The model built with appearance=none equals the one built as before the axis (the renderer without an
    appearance argument, the module without the protocol's): the same parameters, initialised from the same
    random stream, and the same render of the same rays."""
    cfg = tiny_config("appearance=none", *variant)
    before = cfg.copy()
    with open_dict(before):
        del before.model.renderer.appearance, before.model.appearance_fit, before.model.test_protocol
    torch.manual_seed(0)
    now = instantiate(cfg.model)
    torch.manual_seed(0)
    then = instantiate(before.model)
    assert now.renderer.appearance is None
    a, b = now.state_dict(), then.state_dict()
    assert list(a) == list(b)
    for key in a:  # bit for bit (the grid's box is NaN until it is set: NaN equal to NaN)
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, equal_nan=True)
    if now.renderer.grid is not None:
        for m in (now, then):
            m.renderer.grid.set_bounds(torch.tensor([[-1.5] * 3, [1.5] * 3]))
    directions = nn.functional.normalize(torch.randn(32, 3, generator=torch.Generator().manual_seed(1)), dim=-1)
    renders = []
    for m in (now, then):
        with torch.random.fork_rng():
            torch.manual_seed(2)
            renders.append(m.renderer(-4 * directions, directions, deterministic=False))
    for name, out in renders[0].items():
        assert torch.equal(out["rgb"], renders[1][name]["rgb"])


def test_a_renderer_without_codes_refuses_them_and_one_with_codes_defaults_to_its_test_code():
    field = functools.partial(NeRFField, PositionalEncoding(2), functools.partial(MLPViewDependence,
                              direction_encoding=PositionalEncoding(1)), depth=1, width=8, skips=())
    plain = VolumeRenderer(field, HierarchyChoice(True, 4, 4, 8), 2.0, 6.0)
    directions = nn.functional.normalize(torch.randn(3, 3), dim=-1)
    with pytest.raises(ValueError, match="without appearance=embedding"):
        plain(-4 * directions, directions, True, codes=torch.zeros(3, 2))
    embedding = AppearanceEmbedding(dim=2)
    embedding.set_views(4)
    with torch.no_grad():
        embedding.codes.copy_(torch.randn(4, 2))
    coded = VolumeRenderer(field, HierarchyChoice(True, 4, 4, 8), 2.0, 6.0, appearance=embedding)
    default = coded(-4 * directions, directions, True)["fine"]["rgb"]
    given = coded(-4 * directions, directions, True, codes=embedding.test_code().expand(3, -1))["fine"]["rgb"]
    assert torch.equal(default, given)
