"""The ``hierarchical`` flag: the paper's sampling axis as one key, ``true`` (``HierarchicalSampler``: a coarse and a
fine network), ``false`` (``StratifiedSampler``: one network) or ``proposal`` (``ProposalSampler``: mip-NeRF 360's
proposal networks and one network). ``HierarchyChoice`` builds the sampler the flag names, with the sizes each
reads; it is the ``sampler`` config group's default option (``conf/sampler/paper.yaml``), so that
``hierarchical=true,false`` sweeps as a plain key (Hydra refuses booleans as a group's options) while another
option of the group (``sampler=NAME``: a ``Sampler`` class of one's own) replaces it.
"""

from collections.abc import Callable, Mapping
from typing import ClassVar

from nerfexp.domains import COUNT, Applies, Rule, choice
from nerfexp.nerf.proposal import ProposalSampler
from nerfexp.nerf.samplers import HierarchicalSampler, Sampler, StratifiedSampler

HIERARCHIES = (True, False, "proposal")  # the sampling axis: the paper's coarse + fine, one network, proposals
HIERARCHY_SAMPLES = {  # what each choice of the sampling axis reads, as said when another's setting is set
    True: "hierarchical=true (a coarse network of sampler.n_coarse samples and a fine one of n_coarse "
          "+ n_fine; set scale.n_coarse and scale.n_fine)",
    False: "hierarchical=false (one network of sampler.n_single samples; set scale.n_single)",
    "proposal": "hierarchical=proposal (proposal networks choose the samples; set proposal.n_samples and "
                "proposal.n_final)",
}


def hierarchy_reads(reader: bool | str) -> Applies:
    """The reason a ``HierarchyChoice``'s argument is unused unless its ``hierarchical`` is ``reader``, the choice
    that reads it."""
    def reason(config: Mapping) -> str | None:
        return None if config["hierarchical"] == reader else HIERARCHY_SAMPLES[config["hierarchical"]]
    return reason


class HierarchyChoice:
    """Builds (when called, once: the renderer's ``sampler`` argument) the sampler that ``hierarchical`` names:
    ``HierarchicalSampler(n_coarse, n_fine)`` for true, ``StratifiedSampler(n_single)`` for false, ``proposal()``
    (a ``ProposalSampler``) for "proposal"; the sizes of the others are not read (``APPLIES``).

    Args:
        hierarchical: True, False or "proposal".
        n_coarse, n_fine: the hierarchy's samples per ray, of the coarse network and the fine one's extra.
        n_single: the one network's samples per ray without hierarchy.
        proposal: builds the ``ProposalSampler`` (called only for "proposal").
    """

    DOMAINS: ClassVar[dict[str, Rule]] = {
        "hierarchical": choice(*HIERARCHIES),
        "n_coarse": COUNT,
        "n_fine": COUNT,
        "n_single": COUNT,
    }
    APPLIES: ClassVar[dict[str, Applies]] = {
        "n_coarse": hierarchy_reads(True),
        "n_fine": hierarchy_reads(True),
        "n_single": hierarchy_reads(False),
        "proposal": hierarchy_reads("proposal"),
    }

    def __init__(self, hierarchical: bool | str, n_coarse: int, n_fine: int, n_single: int,
                 proposal: Callable[[], ProposalSampler] | None = None):
        if hierarchical not in HIERARCHIES:
            raise ValueError(f"hierarchical: expected true, false or proposal, got {hierarchical!r}")
        if hierarchical == "proposal" and proposal is None:
            raise ValueError("hierarchical=proposal needs the proposal networks (model.renderer.sampler.proposal)")
        self.hierarchical = hierarchical
        self.n_coarse = n_coarse
        self.n_fine = n_fine
        self.n_single = n_single
        self.proposal = proposal

    @staticmethod
    def SAMPLES_PER_RAY(config: Mapping) -> tuple[int, tuple[str, ...]]:
        """The chosen sampler's (its ``SAMPLES_PER_RAY``), the argument names as this config holds them."""
        if config["hierarchical"] == "proposal":
            count, names = ProposalSampler.SAMPLES_PER_RAY(config["proposal"])
            return count, tuple(f"proposal.{name}" for name in names)
        if config["hierarchical"]:
            return HierarchicalSampler.SAMPLES_PER_RAY(config)
        count, _ = StratifiedSampler.SAMPLES_PER_RAY({"n_samples": config["n_single"]})
        return count, ("n_single",)

    def __call__(self) -> Sampler:
        if self.hierarchical == "proposal":
            return self.proposal()
        if self.hierarchical:
            return HierarchicalSampler(self.n_coarse, self.n_fine)
        return StratifiedSampler(self.n_single)
