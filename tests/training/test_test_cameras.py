"""Test cameras refined with the networks frozen (``test_cameras=refined``, TestScorer.refined_camera,
nerfexp.nerf.poses.PoseFit), against a scene whose colour is known in closed form: opaque from the first sample
on, each ray of the colour 0.5 + 0.4 sin(6 d) of its direction d. A camera turned by a known rotation sees another
image; the fit must turn it back (translation changes nothing there, so the rotation alone is determined), leave
every network weight as it was, and use only the pixels the headline protocol does not score apart."""

import functools
import io
import logging
import math
import sys

import pytest
import torch
from torch import nn

from nerfexp.geometry.alignment import rotation_angle
from nerfexp.nerf.appearance import FULL_IMAGE, NERFW_RIGHT_HALF
from nerfexp.nerf.fields import FieldOutputs
from nerfexp.nerf.hierarchy import HierarchyChoice
from nerfexp.nerf.poses import PoseFit, so3_exp
from nerfexp.nerf.volume_renderer import VolumeRenderer
from nerfexp.scoring.scorer import fit_progress_bar
from nerfexp.training.module import NeRFModule

H, W = 16, 16  # rows, columns of the test image
TURN = torch.tensor([0.02, -0.025, 0.015])  # the camera's error, a rotation vector (radians): 1.99 degrees


def colour(directions: torch.Tensor) -> torch.Tensor:
    """The scene's colour [..., 3] seen along unit directions [..., 3]."""
    return 0.5 + 0.4 * torch.sin(6 * directions)


class DirectionColour(nn.Module):
    """Opaque from the first sample on (sigma 1e6), of colour 0.5 + 0.4 sin(6 d) for view direction d; one weight that
    nothing uses, so that the networks have a parameter whose value the test can watch."""

    def __init__(self):
        super().__init__()
        self.unused = nn.Parameter(torch.ones(3))

    def forward(self, positions, directions):
        sigma = torch.full(positions.shape[:-1], 1e6)
        return FieldOutputs(rgb=colour(directions).expand(*sigma.shape, 3), sigma=sigma)


def pinhole_rays() -> tuple[torch.Tensor, torch.Tensor]:
    """A camera at (0, 0, 4) looking down -z with a 60-degree field of view: origins, unit directions [H, W, 3]."""
    j, i = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    focal = W / 2 / math.tan(math.radians(30))
    directions = nn.functional.normalize(torch.stack([(i - W / 2) / focal, -(j - H / 2) / focal,
                                                      -torch.ones(H, W)], -1), dim=-1)
    return torch.tensor([0.0, 0.0, 4.0]).expand(H, W, 3), directions


def turned_batch() -> tuple[dict, torch.Tensor]:
    """The image the true camera sees, with the rays of the camera turned by ``TURN`` about its centre (the given
    camera, wrong by 2 degrees), and the rotation that turned it."""
    origins, directions = pinhole_rays()
    target = colour(directions)
    R = so3_exp(TURN)
    given = (R @ directions[..., None]).squeeze(-1)
    return {"origins": origins.clone(), "directions": given, "rgb": target, "index": 5}, R


def module(protocol: str, fit: PoseFit | None) -> NeRFModule:
    renderer = VolumeRenderer(DirectionColour, HierarchyChoice(True, 4, 4, 8), 2.0, 6.0)
    return NeRFModule(renderer, functools.partial(torch.optim.Adam, lr=1e-3), lr_final=1e-4, chunk=128,
                      lpips=False, test_protocol=protocol, test_camera_fit=fit).eval()


@pytest.mark.parametrize("protocol", [FULL_IMAGE, NERFW_RIGHT_HALF])
def test_a_turned_test_camera_is_turned_back_and_its_image_scores_as_the_true_cameras(protocol):
    batch, R = turned_batch()
    m, plain = module(protocol, PoseFit(steps=120, lr=1e-3, rays=256)), module(protocol, None)
    before = {key: value.clone() for key, value in m.state_dict().items()}
    with torch.inference_mode():  # as Lightning's test loop runs it (the modules built outside it, as Lightning's)
        given = plain.test_step(batch, 0)
        refined_batch, sizes = m.test_scorer().refined_camera(batch)
        scores = m.test_step(batch, 0)
    # the refined rays are the true camera's: the correction undoes the turn to a tenth of a degree
    correction = torch.linalg.lstsq(batch["directions"].reshape(-1, 3),
                                    refined_batch["directions"].reshape(-1, 3)).solution.T
    assert math.degrees(float(rotation_angle((correction @ R).double()))) < 0.1
    assert sizes["camera_fit_deg"] == pytest.approx(math.degrees(float(TURN.norm())), abs=0.1)
    assert sizes["camera_fit_shift"] < 1e-6  # a move changes no colour here: no gradient, no step
    assert scores["psnr"] > given["psnr"] + 15
    assert scores["camera_fit_deg"] == sizes["camera_fit_deg"]
    assert all(torch.equal(before[key], value) for key, value in m.state_dict().items())  # the networks frozen
    assert all(p.grad is None for p in m.parameters())


def test_under_nerfws_protocol_the_camera_is_fitted_on_the_left_half_alone():
    batch, _ = turned_batch()
    spoiled = {**batch, "rgb": batch["rgb"].clone()}
    spoiled["rgb"][:, W // 2:] = torch.rand(H, W - W // 2, 3)  # the scored right half: other content
    fit = PoseFit(steps=20, lr=1e-3, rays=64)
    nerfw, full = module(NERFW_RIGHT_HALF, fit), module(FULL_IMAGE, fit)
    with torch.inference_mode():
        left = nerfw.test_scorer().refined_camera(batch)[0]["directions"]
        left_spoiled = nerfw.test_scorer().refined_camera(spoiled)[0]["directions"]
        whole = full.test_scorer().refined_camera(batch)[0]["directions"]
        whole_spoiled = full.test_scorer().refined_camera(spoiled)[0]["directions"]
    assert torch.equal(left, left_spoiled)  # the right half never seen by the fit
    assert not torch.equal(whole, whole_spoiled)  # the full-image protocol fits on every pixel


def test_given_test_cameras_leave_the_rays_as_they_are():
    batch, _ = turned_batch()
    m = module(FULL_IMAGE, None)
    assert m.test_scorer().refined_camera(batch) == (batch, {})
    assert m.test_cameras == "given" and module(FULL_IMAGE, PoseFit()).test_cameras == "refined"


def test_a_test_image_whose_mask_keeps_nothing_is_scored_from_its_given_camera():
    batch, _ = turned_batch()
    batch["mask"] = torch.zeros(H, W, dtype=torch.bool)
    m = module(FULL_IMAGE, PoseFit(steps=3))
    with torch.inference_mode():
        refined, sizes = m.test_scorer().refined_camera(batch)
    assert refined is batch and sizes == {}


class Terminal(io.StringIO):
    """Standard output as a terminal shows it to tqdm (``isatty``), kept as text."""

    def isatty(self) -> bool:
        return True


def test_a_fit_says_its_start_in_the_log_and_draws_its_steps_where_the_trainer_draws_bars(caplog, monkeypatch):
    batch, _ = turned_batch()
    m = module(FULL_IMAGE, PoseFit(steps=7, rays=16))
    monkeypatch.setattr(sys, "stdout", Terminal())
    with caplog.at_level(logging.INFO, logger="nerfexp"), torch.inference_mode():
        m.test_scorer().refined_camera(batch)
    assert "test view 5: fitting its camera (7 Adam steps of 16 rays)" in caplog.messages
    assert sys.stdout.getvalue() == ""  # no trainer drawing bars (a file, a pipe, enable_progress_bar=false)
    monkeypatch.setattr(m, "_draws_bars", lambda: True)  # as under a trainer whose bar is on (a terminal)
    with torch.inference_mode():
        m.test_scorer().refined_camera(batch)
    assert "test view 5: its camera:   0%|          | 0/7 " in sys.stdout.getvalue()


def test_a_fits_bar_counts_its_steps_and_draws_nothing_where_bars_are_off(monkeypatch):
    monkeypatch.setattr(sys, "stdout", Terminal())
    with fit_progress_bar("test view 2: its appearance code", 4, shown=True) as progress:
        for done in range(1, 5):
            progress(done)
    assert "test view 2: its appearance code:   0%|          | 0/4 " in sys.stdout.getvalue()  # its steps
    monkeypatch.setattr(sys, "stdout", Terminal())
    with fit_progress_bar("test view 2: its appearance code", 4, shown=False) as progress:
        assert progress is None
    assert sys.stdout.getvalue() == ""
