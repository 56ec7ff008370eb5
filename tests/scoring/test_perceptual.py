"""LPIPS (nerfexp.scoring.perceptual) on AlexNet weights each test makes (no test needs, or downloads, the
ImageNet ones): against the lpips package's own network, against a float64 reference written out here, the
[-1, 1] input convention, known-content truths, and the one line or error where the weights are missing and
cannot be downloaded (the download itself: test_lpips_download.py)."""

import hashlib
import importlib.util
import math
import sys
import types
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from nerfexp.errors import ConfigError
from nerfexp.pixels import quantize
from nerfexp.scoring import perceptual
from nerfexp.scoring.perceptual import (
    ALEXNET_FILE,
    HEADS,
    MIN_SIDE,
    ImageTooSmall,
    LpipsNetwork,
    LpipsScorer,
    check_weights_file,
    head_state,
    hub_weights_file,
    lpips_input,
    lpips_network,
    lpips_scorer,
)
from tests.scoring.alexnet import alexnet_state, stand_in, torchvision_alexnet_features
from tests.scoring.weights_server import refused_url


@pytest.fixture
def weights(tmp_path) -> Path:
    """A torchvision-format AlexNet weights file (``alexnet_state``), as ``model.lpips_weights`` names one."""
    path = tmp_path / ALEXNET_FILE
    torch.save(alexnet_state(), path)
    return path


@pytest.fixture
def scorer(weights) -> LpipsScorer:
    return LpipsScorer(lpips_network(weights))


def pair(seed: int = 1, size: tuple[int, int] = (48, 64), noise: float = 0.1) -> tuple[torch.Tensor, torch.Tensor]:
    """An image [H, W, 3] in [0, 1] with smooth structure, and a noisy copy of it."""
    generator = torch.Generator().manual_seed(seed)
    H, W = size
    y, x = torch.meshgrid(torch.linspace(0, 1, H), torch.linspace(0, 1, W), indexing="ij")
    image = torch.stack([x, y, 0.5 + 0.5 * torch.sin(8 * x + 5 * y)], -1)
    noisy = image + noise * torch.randn(image.shape, generator=generator)
    return image, noisy.clamp(0, 1)


def lpips_package():
    """The lpips package (0.1.4), imported. It imports torchvision, whose wheels on PyPI are CUDA builds that
    cannot be imported beside a CPU build of torch (docs/metrics.md): where torchvision is not installed, the
    package gets ``torchvision_alexnet_features`` for the one thing it takes from it, ``models.alexnet``."""
    if importlib.util.find_spec("lpips") is None:  # the README's test command and .ci/run install it
        pytest.fail("the lpips package is not installed: `pip install --no-deps lpips==0.1.4` (its other needs, "
                    "numpy, scipy and tqdm, come with nerfexp; torchvision is not needed)")
    if importlib.util.find_spec("torchvision") is None and "lpips" not in sys.modules:
        def alexnet(pretrained=False, **_):
            assert not pretrained  # pnet_rand=True: the package must not ask for ImageNet weights
            return types.SimpleNamespace(features=torchvision_alexnet_features())
        stand_in = types.ModuleType("torchvision")
        stand_in.models = types.SimpleNamespace(alexnet=alexnet)
        sys.modules["torchvision"] = stand_in
        try:
            import lpips
        finally:
            del sys.modules["torchvision"]
    import lpips
    return lpips


def test_the_lpips_packages_own_network_on_the_same_weights_scores_the_same(weights, scorer):
    lpips = lpips_package()
    theirs = lpips.LPIPS(net="alex", version="0.1", pretrained=True, pnet_rand=True, verbose=False).eval()
    features = {name.removeprefix("features."): value for name, value in torch.load(weights).items()
                if name.startswith("features.")}
    slices = [theirs.net.slice1, theirs.net.slice2, theirs.net.slice3, theirs.net.slice4, theirs.net.slice5]
    for part in slices:  # each slice holds torchvision's layers under their own indices
        part.load_state_dict({name: features[name] for name in part.state_dict()})
    # the same heads: ours are the package's file, unchanged
    assert all(torch.equal(theirs.state_dict()[f"lin{layer}.model.1.weight"], head)
               for layer, head in enumerate(head_state().values()))
    for seed, noise in ((1, 0.02), (2, 0.1), (3, 0.3)):
        image, target = pair(seed, noise=noise)
        a, b = (quantize(x.double()).float().permute(2, 0, 1)[None] for x in (image, target))  # 8-bit images
        with torch.no_grad():
            normalized = theirs(a, b, normalize=True).item()  # its [0, 1] path: 2 x - 1 inside
            scaled = theirs(2 * a - 1, 2 * b - 1).item()  # its documented input: [-1, 1]
        assert scorer(image, target) == pytest.approx(normalized, rel=1e-5, abs=1e-7)
        assert normalized == pytest.approx(scaled, rel=1e-6)


def reference_lpips(state: dict, heads: list[torch.Tensor], image: torch.Tensor, target: torch.Tensor) -> float:
    """LPIPS 0.1 on AlexNet written out in float64 from the paper and the lpips package's code, layer by layer
    from torchvision's state dict: 8-bit images to [-1, 1]; (x - shift) / scale with LPIPS's ScalingLayer
    constants; the five conv + ReLU stages (pools 3/2 after the first two); at each ReLU the feature vectors
    divided by their length + 1e-10; sum over channels of head * squared difference, mean over pixels; summed."""
    shift = torch.tensor([-0.030, -0.088, -0.188], dtype=torch.float64).view(3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450], dtype=torch.float64).view(3, 1, 1)

    def taps(rgb):
        x = ((2 * quantize(rgb.double()) - 1).permute(2, 0, 1) - shift) / scale
        x = x[None]
        found = []
        for index, padding, stride, pool in ((0, 2, 4, True), (3, 2, 1, True), (6, 1, 1, False), (8, 1, 1, False),
                                             (10, 1, 1, False)):
            weight, bias = (state[f"features.{index}.{k}"].double() for k in ("weight", "bias"))
            x = torch.relu(F.conv2d(x, weight, bias, stride=stride, padding=padding))
            found.append(x[0])
            if pool:
                x = F.max_pool2d(x, 3, 2)
        return found

    total = 0.0
    for head, f, g in zip(heads, taps(image), taps(target)):
        fn = f / (torch.sqrt((f * f).sum(0)) + 1e-10)
        gn = g / (torch.sqrt((g * g).sum(0)) + 1e-10)
        total += float((head.double().view(-1, 1, 1) * (fn - gn) ** 2).sum(0).mean())
    return total


@pytest.mark.parametrize("size", [(31, 31), (48, 64), (75, 40)])
def test_equals_a_float64_reference_written_out_layer_by_layer(scorer, size):
    state, heads = alexnet_state(), [h.flatten() for h in head_state().values()]
    image, target = pair(size=size)
    assert scorer(image, target) == pytest.approx(reference_lpips(state, heads, image, target), rel=1e-5)


def test_inputs_reach_the_network_in_minus_one_to_one_after_8_bit_rounding(scorer):
    assert torch.equal(lpips_input(torch.zeros(2, 2, 3)), -torch.ones(1, 3, 2, 2))  # black -> -1
    assert torch.equal(lpips_input(torch.ones(2, 2, 3)), torch.ones(1, 3, 2, 2))  # white -> +1
    # 0.5 / 255 - 1e-6 rounds to 0 (-1 here); 127.6 / 255 rounds to 128 / 255; out-of-range values clamp
    values = torch.tensor([0.5 / 255 - 1e-6, 127.6 / 255, 1.5]).expand(2, 2, 3)  # red, green, blue
    assert torch.allclose(lpips_input(values)[0, :, 0, 0], torch.tensor([-1.0, 2 * 128 / 255 - 1, 1.0]))
    seen = []
    scorer.network.features[0].register_forward_pre_hook(lambda module, args: seen.append(args[0]))
    scorer(torch.zeros(32, 32, 3), torch.ones(32, 32, 3))
    # the first convolution gets (x - shift) / scale of x = -1 (the render) and +1 (the target), per channel
    shift, scale = torch.tensor([-0.030, -0.088, -0.188]), torch.tensor([0.458, 0.448, 0.450])
    assert torch.allclose(seen[0][0, :, 0, 0], (-1 - shift) / scale) and torch.allclose(seen[0][1, :, 0, 0],
                                                                                        (1 - shift) / scale)


def test_identical_images_score_zero_and_the_score_grows_with_noise(scorer):
    image = quantize(pair()[0].double())  # on the 8-bit grid
    assert scorer(image, image) == 0.0
    assert scorer(image, image + 0.4 / 255) == 0.0  # the same 8-bit image
    scores = [scorer(image, pair(noise=noise)[1]) for noise in (0.01, 0.03, 0.1, 0.3)]
    assert all(0 < a < b for a, b in zip(scores, scores[1:])), scores


def test_the_smallest_image_is_31_pixels_on_a_side(scorer):
    # 31 -> conv 11/4/2: 7 -> pool 3/2: 3 -> conv 5/1/2: 3 -> pool 3/2: 1 -> three 3/1/1 convs: 1
    assert [t.shape[-2:] for t in LpipsNetwork().taps(torch.zeros(1, 3, MIN_SIDE, MIN_SIDE))] == [
        (7, 7), (3, 3), (1, 1), (1, 1), (1, 1)]
    assert MIN_SIDE == 31 and math.isfinite(scorer(*pair(size=(31, 40))))
    with pytest.raises(ImageTooSmall, match=r"at least 31 x 31 pixels .*, these are 40 x 30$"):
        scorer(*pair(size=(30, 40)))


def test_a_mixed_precision_evaluation_still_scores_in_float32(scorer):
    image, target = pair()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert scorer(image, target) == scorer(image, target.double())  # float32 whatever comes in


def test_the_heads_are_the_lpips_packages_file_unchanged():
    digest = hashlib.sha256(HEADS.read_bytes()).hexdigest()
    assert digest == "df73285e35b22355a2df87cdb6b70b343713b667eddbda73e1977e0c860835c0"  # lpips 0.1.4's v0.1/alex.pth
    heads = head_state()
    assert [h.shape[1] for h in heads.values()] == [64, 192, 384, 256, 256]
    assert all((h >= 0).all() for h in heads.values())  # LPIPS 0.1 learnt non-negative weights
    assert "Copyright (c) 2018, Richard Zhang" in (HEADS.parent / "lpips_LICENSE.txt").read_text()


@pytest.mark.parametrize(("change", "message"), [
    (lambda s: s.pop("features.3.weight"), "features.3.weight is missing, expected a tensor of shape [192, 64, 5, 5]"),
    (lambda s: s.update({"features.0.bias": torch.zeros(96)}), "features.0.bias is of shape [96], expected a tensor "
                                                               "of shape [64]"),
])
def test_a_file_that_is_not_alexnets_weights_is_one_line_naming_it(tmp_path, change, message):
    state = alexnet_state()
    change(state)
    path = tmp_path / "other.pth"
    torch.save(state, path)
    with pytest.raises(ConfigError) as error:
        lpips_network(path)
    assert str(error.value) == f"{path}: not torchvision's AlexNet ImageNet weights ({ALEXNET_FILE}): {message}"


class Payload:
    """An object whose unpickling would call a function: what a weights file must never do."""

    def __reduce__(self):
        return (print, ("ran",))


@pytest.mark.parametrize("contents", [b"", b"not a checkpoint", Payload(), [1, 2]])
def test_a_damaged_file_or_one_that_would_run_code_is_refused_as_data(tmp_path, capsys, contents):
    path = tmp_path / "weights.pth"
    if isinstance(contents, bytes):
        path.write_bytes(contents)
    else:
        torch.save(contents, path)
    with pytest.raises(ConfigError, match=f"^{path}: not torchvision's AlexNet ImageNet weights") as error:
        lpips_network(path)
    assert "\n" not in str(error.value) and "ran" not in capsys.readouterr().out


def test_without_weights_auto_says_where_it_looked_in_one_line_and_true_refuses(tmp_path, monkeypatch, weights):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))  # an empty hub cache
    monkeypatch.setattr(perceptual, "ALEXNET_URL", refused_url(ALEXNET_FILE))  # offline (test_lpips_download.py)
    cache = hub_weights_file()
    assert cache == tmp_path / "torch" / "hub" / "checkpoints" / ALEXNET_FILE
    none, line = lpips_scorer("auto", None)
    assert none is None and "\n" not in line
    assert line.startswith(f"LPIPS not scored: no AlexNet ImageNet weights at {cache}, and downloading them failed "
                           "(Connection refused): put ")
    assert "model.lpips_weights=FILE" in line and "model.lpips=false" in line
    with pytest.raises(ConfigError, match=f"^model.lpips=true: no AlexNet ImageNet weights at {cache}, and "):
        lpips_scorer(True, None)
    with pytest.raises(ConfigError, match="^model.lpips_weights=/no/such.pth: no such file; expected torchvision's"):
        lpips_scorer("auto", "/no/such.pth")  # a file the config names must be there, even under auto
    assert lpips_scorer(False, "/no/such.pth") == (None, "")
    check_weights_file("auto", None)  # nothing to check: auto reads the hub cache where it has the file

    cache.parent.mkdir(parents=True, exist_ok=True)  # the hub cache filled, as torchvision fills it
    cache.write_bytes(weights.read_bytes())
    stand_in(monkeypatch, weights)  # the test's weights are the published ones here
    for setting in ("auto", True):
        found, line = lpips_scorer(setting, None)
        assert isinstance(found, LpipsScorer) and line == ""
    named, _ = lpips_scorer(True, str(weights))
    image, target = pair()
    assert named(image, target) == found(image, target)
