"""LPIPS only from weights nerfexp can vouch for (nerfexp.scoring.perceptual): every AlexNet weights file, named
in the config or in the torch hub cache, must have the published SHA-256 (``ALEXNET_SHA256``) to score ``lpips``;
any other is refused in one line naming the file and both digests, unless the config says it is the user's own
(``model.lpips_custom=true``), whose scores are ``lpips_custom`` with the file's digest. The files are made here
with AlexNet's keys and shapes (tests/scoring/alexnet.py): the ImageNet file is on no test machine, so a test
that needs "the published weights" makes its own file stand in for them (``stand_in``)."""

import hashlib
import re
import shutil
import tempfile
from pathlib import Path

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nerfexp.errors import ConfigError
from nerfexp.scoring import perceptual
from nerfexp.scoring.perceptual import (
    ALEXNET_FILE,
    ALEXNET_SHA256,
    CUSTOM,
    HEADS,
    HEADS_SHA256,
    PUBLISHED,
    LpipsScorer,
    check_weights_file,
    head_state,
    hub_weights_file,
    lpips_network,
    lpips_scorer,
)
from tests.scoring.alexnet import alexnet_state, stand_in
from tests.scoring.weights_server import refused_url


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def saved(path: Path, seed: int = 0, scale: float = 1.0) -> Path:
    """A file of AlexNet's keys and shapes (``alexnet_state(seed)``, each tensor times ``scale``) at ``path``."""
    torch.save({name: value * scale for name, value in alexnet_state(seed).items()}, path)
    return path


def refusal(path: Path, found: str, remedy: str) -> str:
    return (f"{path}: not torchvision's AlexNet ImageNet weights ({ALEXNET_FILE}): its SHA-256 is {found}, expected "
            f"{perceptual.ALEXNET_SHA256}: {remedy} (docs/metrics.md)")


OWN = ("to score with weights of your own on purpose, add model.lpips_custom=true (recorded as lpips_custom with "
       "the file's SHA-256, never compared with LPIPS)")
HUB = "delete it, and nerfexp downloads the published file there"


@pytest.fixture
def offline_hub(tmp_path, monkeypatch) -> Path:
    """An empty torch hub cache in ``tmp_path`` and no network (the download address refuses): the cache's file."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.setattr(perceptual, "ALEXNET_URL", refused_url(ALEXNET_FILE))
    return hub_weights_file()


def test_the_pinned_digest_begins_with_the_hex_digits_torchvisions_name_carries():
    assert re.fullmatch("[0-9a-f]{64}", ALEXNET_SHA256)
    assert ALEXNET_SHA256.startswith(torch.hub.HASH_REGEX.search(ALEXNET_FILE).group(1))  # what torchvision checks
    assert digest(HEADS) == HEADS_SHA256  # the packaged heads, pinned too


def test_heads_changed_since_nerfexp_was_installed_are_refused_in_one_line(tmp_path):
    changed = tmp_path / HEADS.name
    data = bytearray(HEADS.read_bytes())
    data[-1] ^= 1
    changed.write_bytes(bytes(data))
    with pytest.raises(ConfigError) as error:
        head_state(changed)
    assert str(error.value) == (f"{changed}: not LPIPS 0.1's heads for AlexNet as nerfexp ships them: its SHA-256 is "
                                f"{digest(changed)}, expected {HEADS_SHA256} (reinstall nerfexp)")
    shutil.copyfile(HEADS, changed)
    assert head_state(changed).keys() == head_state().keys()


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2 ** 31 - 1), scale=st.sampled_from([1.0, 0.5, -1.0, 1e-3]),
       setting=st.sampled_from(["auto", True]))
def test_any_file_of_alexnets_keys_and_shapes_but_other_values_is_refused_in_one_line(offline_hub, seed, scale,
                                                                                     setting):
    # named in the config (the 0.0829 against 0.0502) or in the hub cache (the torch hub's name, trusted
    # by its name alone): refused before any work (the settings check) and where LPIPS is set up
    with tempfile.TemporaryDirectory() as folder:
        named = saved(Path(folder) / "other.pth", seed, scale)
        for check in (check_weights_file, lpips_scorer):
            with pytest.raises(ConfigError) as error:
                check(setting, str(named))
            assert str(error.value) == refusal(named, digest(named), OWN)
    offline_hub.parent.mkdir(parents=True, exist_ok=True)
    saved(offline_hub, seed, scale)
    for check in (check_weights_file, lpips_scorer):
        with pytest.raises(ConfigError) as error:
            check(setting, None)
        assert str(error.value) == refusal(offline_hub, digest(offline_hub), HUB)
    offline_hub.unlink()


@pytest.mark.parametrize("setting", ["auto", True])
def test_the_published_weights_score_lpips_from_a_named_file_or_the_hub_cache(offline_hub, tmp_path, monkeypatch,
                                                                              setting):
    named = saved(tmp_path / "copy.pth")
    published = stand_in(monkeypatch, named)
    offline_hub.parent.mkdir(parents=True)
    shutil.copyfile(named, offline_hub)
    for weights in (str(named), None):
        check_weights_file(setting, weights)
        scorer, line = lpips_scorer(setting, weights)
        assert line == "" and scorer.metric == PUBLISHED and scorer.weights_sha256 == published


@pytest.mark.parametrize("setting", ["auto", True])
def test_own_weights_on_purpose_score_as_lpips_custom_with_their_digest(offline_hub, tmp_path, setting):
    own = saved(tmp_path / "own.pth", seed=5)
    check_weights_file(setting, str(own), custom=True)
    scorer, line = lpips_scorer(setting, str(own), custom=True)
    assert line == "" and scorer.metric == CUSTOM and scorer.weights_sha256 == digest(own)
    image = torch.rand(32, 40, 3, generator=torch.Generator().manual_seed(0))
    target = image.flip(0)
    assert scorer(image, target) == LpipsScorer(lpips_network(own))(image, target) > 0
    assert not offline_hub.exists()  # a named file: nothing downloaded, no cache read


def test_the_name_follows_the_bytes_loaded_not_the_setting(tmp_path, monkeypatch):
    # lpips_custom=true with the published file: it is LPIPS, and is recorded as such
    named = saved(tmp_path / "copy.pth")
    stand_in(monkeypatch, named)
    scorer, _ = lpips_scorer(True, str(named), custom=True)
    assert scorer.metric == PUBLISHED


@pytest.mark.parametrize("setting", ["auto", True])
def test_own_weights_need_a_file_named(offline_hub, setting):
    for check in (check_weights_file, lpips_scorer):
        with pytest.raises(ConfigError) as error:
            check(setting, None, custom=True)
        assert str(error.value) == (
            "model.lpips_custom=true says the AlexNet weights model.lpips_weights names are your own, and it names "
            "none: set model.lpips_weights=FILE, or drop model.lpips_custom (docs/metrics.md)")
    check_weights_file(False, None, custom=True)  # LPIPS off: nothing read
    assert lpips_scorer(False, None, custom=True) == (None, "")


def test_a_file_changed_after_the_settings_check_is_refused_when_it_is_loaded(tmp_path, monkeypatch):
    named = saved(tmp_path / "copy.pth")
    stand_in(monkeypatch, named)
    check_weights_file(True, str(named))  # the settings check, before the run's directory is made
    saved(named, seed=9)  # replaced before LPIPS is set up
    with pytest.raises(ConfigError) as error:
        lpips_scorer(True, str(named))
    assert str(error.value) == refusal(named, digest(named), OWN)
    with pytest.raises(ConfigError) as error:
        lpips_network(named, perceptual.ALEXNET_SHA256)  # the digest is of the very bytes it loads
    assert str(error.value) == refusal(named, digest(named), OWN)


@pytest.mark.parametrize("make", [lambda path: path.mkdir(), lambda path: path.symlink_to(path.parent / "none")])
def test_a_path_that_is_not_a_weights_file_is_one_line(tmp_path, make):
    path = tmp_path / "weights.pth"
    make(path)
    with pytest.raises(ConfigError, match=f"^model.lpips_weights={path}: no such file; expected torchvision's"):
        check_weights_file("auto", str(path), custom=True)


def test_a_file_larger_than_any_weights_file_is_refused_unread(tmp_path, monkeypatch):
    path = saved(tmp_path / "large.pth")
    monkeypatch.setattr(perceptual, "WEIGHTS_BYTES", 1000)
    for check in (check_weights_file, lpips_scorer):
        with pytest.raises(ConfigError) as error:
            check(True, str(path), custom=True)
        assert str(error.value) == f"{path}: larger than the 1,000 bytes nerfexp reads of such a file"


def test_own_weights_not_of_alexnets_keys_and_shapes_are_refused_before_any_work(tmp_path):
    state = alexnet_state()
    state["features.3.weight"] = torch.zeros(192, 64, 3, 3)
    path = tmp_path / "own.pth"
    torch.save(state, path)
    with pytest.raises(ConfigError) as error:
        check_weights_file("auto", str(path), custom=True)
    assert str(error.value) == (f"{path}: not torchvision's AlexNet ImageNet weights ({ALEXNET_FILE}): "
                                "features.3.weight is of shape [192, 64, 3, 3], expected a tensor of shape "
                                "[192, 64, 5, 5]")
