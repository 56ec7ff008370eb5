"""The components' interfaces: an encoding, a colour head and a sampler are each a small base class; fields
answer named outputs; a component's settings (``DOMAINS``, ``APPLIES``) are declared beside its class, name its
constructor's arguments and hold the limits worked out by hand here."""

import functools
import inspect

import pytest
import torch

from nerfexp.nerf.encodings import Encoding, IdentityEncoding, PositionalEncoding
from nerfexp.nerf.fields import (
    DensityField,
    FieldOutputs,
    MLPViewDependence,
    NeRFField,
    NoViewDependence,
    SphericalHarmonicsViewDependence,
    ViewDependence,
)
from nerfexp.nerf.hashgrid import HashGridEncoding
from nerfexp.nerf.hierarchy import HIERARCHIES, HierarchyChoice
from nerfexp.nerf.occupancy import OccupancyGrid
from nerfexp.nerf.proposal import ProposalSampler
from nerfexp.nerf.reflection import ReflectionViewDependence
from nerfexp.nerf.samplers import HierarchicalSampler, Sampler, StratifiedSampler
from nerfexp.nerf.volume_renderer import VolumeRenderer
from tests.analytic import rays_down_z, slab

CONFIGURED = [PositionalEncoding, IdentityEncoding, HashGridEncoding, MLPViewDependence, NoViewDependence,
              SphericalHarmonicsViewDependence, ReflectionViewDependence, DensityField, NeRFField, ProposalSampler,
              HierarchyChoice, VolumeRenderer, OccupancyGrid]
BOX = [[-1.0] * 3, [1.0] * 3]


@pytest.mark.parametrize("component", CONFIGURED, ids=lambda c: c.__name__)
def test_a_components_declared_settings_are_its_constructors_arguments_and_take_its_defaults(component):
    parameters = inspect.signature(component).parameters
    assert set(component.DOMAINS) <= set(parameters) and set(getattr(component, "APPLIES", {})) <= set(parameters)
    for name, (_, test) in component.DOMAINS.items():
        default = parameters[name].default
        if default is not inspect.Parameter.empty:
            assert test(list(default) if isinstance(default, tuple) else default), name  # a config writes lists


# exp and softplus of a raw density of 88 are finite in float32, of 89 not: the raw offsets' limit
assert torch.isfinite(torch.exp(torch.tensor(88.0))) and torch.isinf(torch.exp(torch.tensor(89.0)))


@pytest.mark.parametrize(("component", "argument", "accepted", "refused"), [
    (HashGridEncoding, "log2_table_size", [1, 30], [0, 31, 19.0, True]),
    (HashGridEncoding, "finest", [1, 2**20 - 1], [0, 2**20]),  # a cell's corner times a prime within int64
    (HashGridEncoding, "sparse_gradients", [True, False], [1, "true"]),
    (PositionalEncoding, "n_freqs", [0, 10], [-1, 1.5]),
    (PositionalEncoding, "input_scale", [2.0**-4, 2**18], [0, -1, 2**18 + 1, float("inf")]),
    (SphericalHarmonicsViewDependence, "degree", [0, 3], [-1, 4]),  # sh_basis writes bands 0 to 3
    (ReflectionViewDependence, "n_levels", [1, 6], [0, 7]),
    (ReflectionViewDependence, "normal_weight", [0, 2**24], [-1e-9, 2**24 + 1]),
    (MLPViewDependence, "hidden", [1], [0, 1.0]),
    (NeRFField, "density_bias", [-88, 88], [-89, 88.5, float("nan")]),
    (NeRFField, "density_noise_std", [0, 88], [-0.1, 89]),
    (NeRFField, "skips", [[], [0, 5]], [[-1], 5]),
    (NeRFField, "density_activation", ["relu", "softplus", "trunc_exp"], ["exp", None]),
    (DensityField, "depth", [1, 2**63 - 1], [0, 2**63]),
    (ProposalSampler, "n_samples", [[64, 64], [1]], [[], [0], 64]),
    (ProposalSampler, "interlevel_weight", [1e-9, 2**24], [0, -1]),  # it alone trains the proposals: never 0
    (ProposalSampler, "distortion_weight", [0, 0.01], [-0.01]),
    (HierarchyChoice, "hierarchical", [True, False, "proposal"], ["true", 1, 0, "coarse"]),
    (VolumeRenderer, "near", [None, 0, 2**24], [-1, 2**24 + 1]),  # None: from the scene
    (VolumeRenderer, "far", [None, 1e-9, 2**24], [0, 2**24 + 1]),
    (VolumeRenderer, "background", ["white", "black"], ["grey", None]),
    (HierarchyChoice, "n_single", [1], [0]),
    (OccupancyGrid, "threshold", [1e-9, 1], [0, 1.5]),
    (OccupancyGrid, "warmup_steps", [0], [-1]),
])
def test_a_components_domains_hold_its_limits(component, argument, accepted, refused):
    expected, test = component.DOMAINS[argument]
    assert isinstance(expected, str) and expected
    assert [v for v in accepted if not test(v)] == [] and [v for v in refused if test(v)] == []


def test_the_sample_counts_and_proposals_apply_only_under_the_sampler_that_reads_them():
    said = {True: "hierarchical=true (a coarse network of sampler.n_coarse samples and a fine one of "
                  "n_coarse + n_fine; set scale.n_coarse and scale.n_fine)",
            False: "hierarchical=false (one network of sampler.n_single samples; set scale.n_single)",
            "proposal": "hierarchical=proposal (proposal networks choose the samples; set proposal.n_samples and "
                        "proposal.n_final)"}
    reads = {True: {"n_coarse", "n_fine"}, False: {"n_single"}, "proposal": {"proposal"}}
    for hierarchical in HIERARCHIES:
        reasons = {argument: applies({"hierarchical": hierarchical})
                   for argument, applies in HierarchyChoice.APPLIES.items()}
        assert {a for a, reason in reasons.items() if reason is None} == reads[hierarchical]
        assert {reason for reason in reasons.values() if reason is not None} == {said[hierarchical]}


@pytest.mark.parametrize(("hierarchical", "sampler", "names", "samples", "final"), [
    (True, HierarchicalSampler, ("coarse", "fine"), 8 + (8 + 16), 8 + 16),
    (False, StratifiedSampler, ("coarse",), 24, 24),
    ("proposal", ProposalSampler, ("coarse",), 8 + 8 + 12, 12),
])
def test_each_choice_of_hierarchical_renders_through_its_sampler(hierarchical, sampler, names, samples, final):
    proposal = functools.partial(ProposalSampler, slab, n_samples=[8, 8], n_final=12)
    renderer = VolumeRenderer(slab,
                              HierarchyChoice(hierarchical, n_coarse=8, n_fine=16, n_single=24, proposal=proposal),
                              near=2.0, far=6.0)
    assert type(renderer.sampler) is sampler and isinstance(renderer.sampler, Sampler)
    out = renderer(*rays_down_z(3), deterministic=True)
    assert tuple(out) == renderer.sampler.field_names == names and (renderer.fine is not None) == ("fine" in names)
    assert out[names[-1]]["t_starts"].shape == (3, final)  # the samples the final network evaluated
    assert renderer.samples_per_ray == renderer.stats["samples_per_ray"] == samples  # no grid: every one evaluated


@pytest.mark.parametrize("hierarchical", HIERARCHIES)
def test_checkpoints_hold_the_networks_under_their_names_and_the_samplers_own_under_sampler(hierarchical):
    field = functools.partial(NeRFField, IdentityEncoding(), NoViewDependence, depth=1, width=4, skips=())
    network = functools.partial(DensityField, IdentityEncoding(), depth=1, width=4, skips=())
    proposal = functools.partial(ProposalSampler, network, n_samples=[8, 8], n_final=8)
    renderer = VolumeRenderer(field, HierarchyChoice(hierarchical, 8, 8, 8, proposal=proposal), near=2.0, far=6.0)
    one = {"trunk.0.weight", "trunk.0.bias", "sigma.weight", "sigma.bias"}
    expected = {f"{name}.{key}" for name in renderer.sampler.field_names for key in one | {"view_head.rgb.weight",
                                                                                          "view_head.rgb.bias"}}
    if hierarchical == "proposal":
        expected |= {f"sampler.networks.{i}.{key}" for i in (0, 1) for key in one}
    assert set(renderer.state_dict()) == expected


@pytest.mark.parametrize("head", [
    functools.partial(MLPViewDependence, direction_encoding=PositionalEncoding(2), hidden=8), NoViewDependence,
    functools.partial(SphericalHarmonicsViewDependence, degree=1),
    functools.partial(ReflectionViewDependence, hidden=8, n_levels=2)], ids=["mlp", "none", "sh", "ref"])
def test_colour_heads_share_one_interface_and_the_field_names_its_outputs(head):
    torch.manual_seed(0)
    field = NeRFField(PositionalEncoding(2), head, depth=2, width=16, skips=())
    x, d = torch.randn(5, 3), torch.nn.functional.normalize(torch.randn(5, 3), dim=-1)
    out = field(x, d)
    names = field.view_head.penalty_names
    assert isinstance(field.view_head, ViewDependence) and isinstance(out, FieldOutputs)
    assert out.rgb.shape == (5, 3) and torch.equal(out.sigma, field.density(x))
    assert field.view_head.uses_normals == (names != ()) and field.view_head.penalty_weights.shape == (len(names),)
    assert (out.penalties is None) == (names == ()) and (names == () or out.penalties.shape == (5, len(names)))
    with torch.no_grad():  # no density gradient to compare the normals with: no penalties
        assert field(x, d).penalties is None
    if names == ():
        with pytest.raises(NotImplementedError, match="predicts no normals"):
            field.view_head.penalties(d, d, d)


def test_an_encoding_names_its_own_parameter_groups_and_gradients():
    grid = HashGridEncoding(n_levels=3, log2_table_size=6, coarsest=2, finest=16, aabb=BOX)
    assert len(grid.dense) == 1 and grid.hashed.shape[0] == 2  # (2 + 1)^3 <= 64 < (4 + 1)^3
    groups = grid.parameter_groups()
    assert list(groups) == ["hash_tables"] and groups["hash_tables"]["weight_decay"] == 0.0
    # every table, in parameters()' order (the module's own parameter, then its ParameterList's)
    assert [id(p) for p in groups["hash_tables"]["params"]] == [id(grid.hashed), id(grid.dense[0])]
    assert not grid.sparse_gradients
    assert HashGridEncoding(n_levels=3, log2_table_size=6, coarsest=2, finest=16, aabb=BOX,
                            sparse_gradients=True).sparse_gradients
    for encoding in (PositionalEncoding(4), IdentityEncoding(), grid):
        assert isinstance(encoding, Encoding) and encoding(torch.zeros(2, 3)).shape == (2, encoding.out_dim)
    assert PositionalEncoding(4).parameter_groups() == IdentityEncoding().parameter_groups() == {}
    assert not PositionalEncoding(4).sparse_gradients
