"""LPIPS (Zhang et al., CVPR 2018), version 0.1 on AlexNet: the perceptual distance NeRF papers report beside
PSNR and SSIM (0 for identical images, larger for images less alike), written out in torch so that it needs
neither the ``lpips`` package nor torchvision (docs/metrics.md says why).

Images ``x``, ``y`` [N, 3, H, W] in [-1, 1] (the lpips package's convention; ``lpips_input`` makes them from
[H, W, 3] in [0, 1]) are shifted and scaled per channel (``SHIFT``, ``SCALE``: LPIPS 0.1's ScalingLayer) and
run through AlexNet's convolutions; at each of its five ReLUs l (``TAPS``, C_l = 64, 192, 384, 256, 256
channels) every pixel's feature vector is divided by its length over the channels (+ 1e-10), and

    LPIPS(x, y) = sum_l mean_{h, w} sum_c w_{l,c} (f_l(x) - f_l(y))_{c,h,w}^2

with w_l >= 0 the linear heads LPIPS 0.1 learnt (``HEADS``: the lpips package's ``weights/v0.1/alex.pth``,
shipped here unchanged with its BSD-2-Clause notice, ``lpips_LICENSE.txt``).

AlexNet's weights are torchvision's ImageNet ones (``ALEXNET_FILE``), read as data
(``torch.load(weights_only=True)``) from a file named in the config (``weights_file``), else from the torch hub
cache, where torchvision keeps them, and scored as ``lpips`` only where the file's SHA-256 is theirs
(``ALEXNET_SHA256``), wherever it comes from: the digest is taken of the very bytes that are loaded
(``lpips_network``). A file of other values is refused in one line (``mismatch``), unless the config says the
weights are the user's own on purpose (``model.lpips_custom=true``): its scores are then ``lpips_custom`` (``CUSTOM``),
recorded with the file's SHA-256 and never compared with LPIPS. Where the cache lacks the weights, nerfexp
downloads them there once, from torchvision's address (``ALEXNET_URL``), checked as the file is (``fetch_alexnet``:
the name's hash prefix, as torchvision checks, and the whole SHA-256 before the file takes its name), waiting at
most ``TIMEOUT_S`` for the server to answer: when LPIPS is set up (under ``model.lpips=true`` when the settings
are checked), never on import and never where the config names a file. Offline, LPIPS is not scored under
``model.lpips=auto`` (one line says why) and is an error under ``true``.
"""

import hashlib
import http.client
import logging
import math
import os
import socket
import uuid
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from urllib.error import URLError
from urllib.parse import urlsplit

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from nerfexp.downloads import DownloadFailed, failure_reason
from nerfexp.errors import ConfigError
from nerfexp.pixels import quantize
from nerfexp.reading import UnreadableFile, read_bytes
from nerfexp.rundir.trained import load_as_data

HEADS = Path(__file__).with_name("lpips_alex_v0.1.pth")  # LPIPS 0.1's linear heads for AlexNet
ALEXNET_FILE = "alexnet-owt-7be5be79.pth"  # torchvision's AlexNet ImageNet weights, as its hub cache names them
ALEXNET_URL = f"https://download.pytorch.org/models/{ALEXNET_FILE}"  # where torchvision downloads them from
# Their whole SHA-256. torchvision publishes only its first 8 hex digits, in the file's name; the whole digest is the
# one Hugging Face shows for copies of the file (huggingface.co/blanchon/image-gs-models-utils and
# huggingface.co/CSWRY/VOSR, torch/checkpoints/alexnet-owt-7be5be79.pth, 244 MB), which starts with those 8 digits
ALEXNET_SHA256 = "7be5be791159472b1fbf3c69796f7cb30dca7ad8466c2df70058c37116cdee02"
HEADS_SHA256 = "df73285e35b22355a2df87cdb6b70b343713b667eddbda73e1977e0c860835c0"  # lpips 0.1.4's weights/v0.1/alex.pth
WEIGHTS_BYTES = 1 << 30  # the largest weights file read: torchvision's AlexNet file is 233 MiB (float32)
TIMEOUT_S = 15  # seconds a download waits for the server to connect or send more (pip's default --timeout)
SHIFT = (-0.030, -0.088, -0.188)  # LPIPS 0.1's per-channel shift and scale of [-1, 1] inputs
SCALE = (0.458, 0.448, 0.450)
TAPS = (1, 4, 7, 9, 11)  # the layers of ``alexnet_features`` whose outputs are compared: its five ReLUs
CHANNELS = (64, 192, 384, 256, 256)  # their channels
MIN_SIDE = 31  # the smallest image side that leaves the last ReLU one pixel (``alexnet_features``)
EPS = 1e-10  # added to each feature vector's length before dividing, as LPIPS does
SETTINGS = ("auto", True, False)  # model.lpips: scored where the weights are found or downloaded; required; off
NOT_SCORED = math.nan  # an image's LPIPS where it is not scored (the recorders leave it out of their files)
PUBLISHED, CUSTOM = "lpips", "lpips_custom"  # the scores' names: with the published weights; with the user's own
LPIPS_NAMES = (PUBLISHED, CUSTOM)  # every name an LPIPS score is recorded under

log = logging.getLogger(__name__)


class ImageTooSmall(ConfigError):
    """An image below ``MIN_SIDE`` pixels on a side, which AlexNet's strides and pools reduce to nothing."""


class UnreadableWeights(ConfigError):
    """A weights file that is there and cannot be read as one (``weights_bytes``): the message names it and why."""


def alexnet_features() -> nn.Sequential:
    """torchvision's ``AlexNet.features`` up to its fifth ReLU, layer for layer, so that layer ``i`` here is
    ``features.i`` in torchvision's state dict (its last max pool, which LPIPS does not use, left out).
    A side of s pixels comes out of the first convolution (11 wide, stride 4, padding 2) as
    floor((s - 7) / 4) + 1 and out of each 3-wide stride-2 pool as floor((s - 3) / 2) + 1: s = 31 is the
    smallest that leaves the last layers a pixel (31 -> 7 -> 3 -> 3 -> 1), ``MIN_SIDE``."""
    return nn.Sequential(
        nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2), nn.ReLU(),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(64, 192, kernel_size=5, padding=2), nn.ReLU(),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(192, 384, kernel_size=3, padding=1), nn.ReLU(),
        nn.Conv2d(384, 256, kernel_size=3, padding=1), nn.ReLU(),
        nn.Conv2d(256, 256, kernel_size=3, padding=1), nn.ReLU(),
    )


def unit_features(features: Tensor) -> Tensor:
    """Each pixel's feature vector of ``features`` [N, C, H, W] divided by its length over C (+ ``EPS``)."""
    return features / (features.square().sum(1, keepdim=True).sqrt() + EPS)


class LpipsNetwork(nn.Module):
    """LPIPS 0.1 on AlexNet (the module's docstring): ``forward(x, y)`` of images [N, 3, H, W] in [-1, 1]
    is their distances [N]. Its weights are fixed: ``features`` (``alexnet_features``, from torchvision's
    state dict) and the heads ``head_{l}`` [1, C_l, 1, 1], buffers. Built empty; ``lpips_network`` loads it
    and sets ``weights_sha256``, the SHA-256 of the AlexNet weights file it loaded."""

    def __init__(self):
        super().__init__()
        self.weights_sha256: str | None = None  # set where the weights are loaded (lpips_network)
        self.features = alexnet_features().requires_grad_(False)
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))
        for layer, channels in enumerate(CHANNELS):
            self.register_buffer(f"head_{layer}", torch.zeros(1, channels, 1, 1))

    def taps(self, images: Tensor) -> list[Tensor]:
        """The outputs of the five ReLUs (``TAPS``) for ``images`` [N, 3, H, W] in [-1, 1]."""
        x, found = (images - self.shift) / self.scale, []
        for index, layer in enumerate(self.features):
            x = layer(x)
            if index in TAPS:
                found.append(x)
        return found

    def forward(self, x: Tensor, y: Tensor) -> Tensor:
        N = x.shape[0]
        distance = torch.zeros(N, dtype=x.dtype, device=x.device)
        for layer, both in enumerate(self.taps(torch.cat([x, y]))):  # one pass for the two: [2N, C_l, H_l, W_l]
            squared = (unit_features(both[:N]) - unit_features(both[N:])).square()
            distance = distance + F.conv2d(squared, getattr(self, f"head_{layer}")).mean((1, 2, 3))
        return distance


def url_file_name(url: str) -> str:
    """The file name ``url`` ends with, as torch hub names the file it downloads (``ALEXNET_FILE`` for
    ``ALEXNET_URL``)."""
    return urlsplit(url).path.rsplit("/", 1)[-1]


def hub_weights_file() -> Path:
    """Where torchvision keeps AlexNet's ImageNet weights once downloaded, and where ``fetch_alexnet`` puts them:
    the torch hub cache (``$TORCH_HOME/hub``, by default ``~/.cache/torch/hub``),
    ``checkpoints/alexnet-owt-7be5be79.pth`` (the name ``ALEXNET_URL`` ends with, read when called)."""
    return Path(torch.hub.get_dir()) / "checkpoints" / url_file_name(ALEXNET_URL)


def download_failure(error: Exception, path: Path | None = None) -> str:
    """Why a download failed, in a few words, from the error ``torch.hub.download_url_to_file`` raised: a failed
    hash check (which is also what a body cut short gives: urllib stops reading at its end without an error), a
    local failure of the file being downloaded ("cannot write ``path``": a full disk, a cache directory it may not
    write; never the temporary file the error names), else what ``nerfexp.downloads.failure_reason`` says of it (an
    HTTP status, no network, a broken connection)."""
    if isinstance(error, RuntimeError):  # the only one download_url_to_file raises: its hash check
        return "SHA-256 check failed: a truncated or altered download"
    local = isinstance(error, OSError) and not isinstance(error, URLError)  # HTTPError is an OSError with a filename
    if local and error.filename is not None and path is not None:  # a temporary file's
        return f"cannot write {path} ({error.strerror or error})"
    return failure_reason(error)


@contextmanager
def socket_timeout(seconds: float) -> Iterator[None]:
    """Within the block, a connection that does not connect, or stops sending, for ``seconds`` fails with a
    TimeoutError: the process's default socket timeout, which ``torch.hub.download_url_to_file`` (whose
    ``urlopen`` takes none of its own) waits for, set for the block and put back after it (process-wide while it
    holds: a socket another thread opens meanwhile gets it too; nerfexp opens none then)."""
    before = socket.getdefaulttimeout()
    socket.setdefaulttimeout(seconds)
    try:
        yield
    finally:
        socket.setdefaulttimeout(before)


def folder_failure(folder: Path, error: OSError) -> str:
    """Why the folder ``folder`` could not be made (``error``, from ``Path.mkdir(parents=True)``), naming the real
    place: the first path above it (or itself) that is there and not a folder (``TORCH_HOME`` set to a file), else
    the folder the system could not make and the system's words (a folder you may not write).

    >>> folder_failure(Path("/dev/null/hub/checkpoints"), NotADirectoryError(20, "Not a directory"))
    '/dev/null is not a folder'
    """
    for above in (*reversed(folder.parents), folder):
        if os.path.lexists(above) and not os.path.isdir(above):
            return f"{above} is not a folder"
    return f"cannot make the folder {error.filename or folder} ({error.strerror or error})"


def fetch_alexnet(cache_dir: Path, url: str | None = None, expected: str | None = None) -> Path:
    """The file at ``url`` (None: ``ALEXNET_URL``) downloaded into ``cache_dir`` (made where missing) under the
    name the URL ends with, ``cache_dir / url_file_name(url)``, which it returns, once its SHA-256 is ``expected``
    (None: ``ALEXNET_SHA256``; both read when called). The name's hex digits (``name-<hex>.ext``, torch hub's
    ``HASH_REGEX``: 7be5be79 in ``ALEXNET_FILE``) must begin it, as torchvision checks its downloads.
    ``torch.hub.download_url_to_file`` downloads it, with its progress bar, waiting at most ``TIMEOUT_S`` for the
    server to connect or send more (``socket_timeout``), into ``<name>.<uuid>.partial`` in ``cache_dir`` (deleted
    on any failure), then to ``<name>.<uuid>.unchecked`` (this call's own: the processes of a distributed run may
    download at once), which takes the name only once its whole SHA-256 matches, and is deleted otherwise: the
    name never holds a partial or altered file. Downloads whatever is at the name already again: callers fetch
    only a file that is missing. A ``DownloadFailed`` saying why in a few words where it cannot, naming the real
    file or folder, never a temporary one (``folder_failure`` where ``cache_dir`` cannot be made, else
    ``download_failure``); a ValueError for a name without a hash, or one whose hash ``expected`` does not begin
    with."""
    url = ALEXNET_URL if url is None else url
    expected = ALEXNET_SHA256 if expected is None else expected
    name = url_file_name(url)
    found = torch.hub.HASH_REGEX.search(name)
    if found is None or not found.group(1):
        raise ValueError(f"{url}: its file name carries no hash to check (name-<hex>.ext)")
    if not expected.startswith(found.group(1)):
        raise ValueError(f"{url}: its file name's hash {found.group(1)} does not begin the SHA-256 {expected}")
    path = Path(cache_dir) / name
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise DownloadFailed(folder_failure(path.parent, error)) from error
    unchecked = path.with_name(f"{name}.{uuid.uuid4().hex}.unchecked")
    try:  # no line before: offline, the caller's one line is all (the progress bar shows once bytes arrive)
        with socket_timeout(TIMEOUT_S):
            torch.hub.download_url_to_file(url, str(unchecked), hash_prefix=found.group(1), progress=True)
        digest = hashlib.sha256(unchecked.read_bytes()).hexdigest()
        if digest != expected:
            raise DownloadFailed(f"SHA-256 check failed: {digest}, expected {expected}")
        os.replace(unchecked, path)
    except (OSError, http.client.HTTPException, RuntimeError, ValueError) as error:
        raise DownloadFailed(download_failure(error, path)) from error
    finally:
        with suppress(OSError):  # none made (a folder it may not write): nothing to remove
            unchecked.unlink(missing_ok=True)
    log.info("AlexNet's ImageNet weights for LPIPS downloaded, once, from %s to %s", url, path)
    return path


def weights_file(weights: str | Path | None) -> Path:
    """The file AlexNet's weights are read from: ``weights`` (``model.lpips_weights``), else the hub cache's."""
    return Path(weights).expanduser() if weights is not None else hub_weights_file()


def weights_bytes(path: Path) -> tuple[bytes, str]:
    """The bytes of the weights file ``path`` (``nerfexp.reading.read_bytes``: a regular file of at most
    ``WEIGHTS_BYTES``) and their SHA-256 (hexadecimal); an ``UnreadableWeights`` (a ConfigError) naming the file
    where it cannot be read so."""
    try:
        data = read_bytes(path, WEIGHTS_BYTES)
    except UnreadableFile as error:
        raise UnreadableWeights(str(error)) from None
    return data, hashlib.sha256(data).hexdigest()


def mismatch(path: Path, found: str) -> str:
    """Why the AlexNet weights file ``path``, whose SHA-256 is ``found``, is not read, in one line: the expected and
    found digests, and what to do (the hub cache's: delete it, so that the published file is downloaded there)."""
    remedy = ("delete it, and nerfexp downloads the published file there" if Path(path) == hub_weights_file() else
              "to score with weights of your own on purpose, add model.lpips_custom=true (recorded as lpips_custom "
              "with the file's SHA-256, never compared with LPIPS)")
    return (f"{path}: not torchvision's AlexNet ImageNet weights ({ALEXNET_FILE}): its SHA-256 is {found}, expected "
            f"{ALEXNET_SHA256}: {remedy} (docs/metrics.md)")


def read_state(path: Path, what: str, data: bytes | None = None) -> dict:
    """The state dict in ``path`` read as data (``nerfexp.rundir.trained.load_as_data``; ``data``: its bytes,
    where the caller has read them to check them); a ConfigError naming the file and ``what`` was expected
    otherwise."""
    state = load_as_data(path, what, "weight files", ConfigError, data)
    if not isinstance(state, dict):
        raise ConfigError(f"{path}: not {what} (a state dict of tensors)")
    return state


def backbone_state(path: Path, data: bytes | None = None) -> dict[str, Tensor]:
    """AlexNet's convolution weights ``features.{i}.weight``/``bias`` from torchvision's state dict in ``path``
    (``data``: its bytes, where already read; its classifier's entries, which LPIPS does not use, left aside); a
    ConfigError naming the file and the first entry missing or of another shape."""
    what = f"torchvision's AlexNet ImageNet weights ({ALEXNET_FILE})"
    state = read_state(path, what, data)
    expected = {f"features.{name}": value for name, value in alexnet_features().state_dict().items()}
    for name, value in expected.items():
        found = state.get(name)
        if not isinstance(found, Tensor) or found.shape != value.shape:
            got = "missing" if found is None else (
                f"of shape {list(found.shape)}" if isinstance(found, Tensor) else "not a tensor")
            raise ConfigError(f"{path}: not {what}: {name} is {got}, expected a tensor of shape {list(value.shape)}")
    return {name: state[name].float() for name in expected}


def head_state(path: Path = HEADS) -> dict[str, Tensor]:
    """LPIPS 0.1's heads for AlexNet as ``LpipsNetwork`` names them (``head_{l}`` [1, C_l, 1, 1]) from the lpips
    package's file (its keys ``lin{l}.model.1.weight``), whose SHA-256 must be ``HEADS_SHA256`` (a ConfigError
    naming the file otherwise: an installation changed since)."""
    data, found = weights_bytes(path)
    if found != HEADS_SHA256:
        raise ConfigError(f"{path}: not LPIPS 0.1's heads for AlexNet as nerfexp ships them: its SHA-256 is {found}, "
                          f"expected {HEADS_SHA256} (reinstall nerfexp)")
    state = read_state(path, "LPIPS 0.1's heads for AlexNet", data)
    return {f"head_{layer}": state[f"lin{layer}.model.1.weight"].float() for layer in range(len(CHANNELS))}


def lpips_network(weights: Path, expected: str | None = None) -> LpipsNetwork:
    """``LpipsNetwork`` with AlexNet's weights from the file ``weights`` (torchvision's state dict) and LPIPS 0.1's
    heads, in eval mode on the CPU, its ``weights_sha256`` the digest of the bytes loaded (read once: what is
    checked is what is loaded). ``expected``: the digest the file must have (``ALEXNET_SHA256`` for the published
    weights; a ConfigError, ``mismatch``, where it has another), or None for weights of the user's choosing
    (``model.lpips_custom=true``), whose digest the network keeps for the records."""
    data, found = weights_bytes(weights)
    if expected is not None and found != expected:
        raise ConfigError(mismatch(weights, found))
    network = LpipsNetwork()
    network.features.load_state_dict({name.removeprefix("features."): value
                                      for name, value in backbone_state(weights, data).items()})
    for name, head in head_state().items():
        getattr(network, name).copy_(head)
    network.weights_sha256 = found
    return network.eval()


def lpips_input(image: Tensor) -> Tensor:
    """An image [H, W, 3] in [0, 1] as LPIPS takes it: quantized to 8 bits as PSNR and SSIM score it
    (``nerfexp.pixels.quantize``, in float64), then 2 x - 1: [1, 3, H, W] in [-1, 1], float32 (black -1,
    white +1)."""
    return (2 * quantize(image.double()) - 1).float().permute(2, 0, 1).unsqueeze(0)


class LpipsScorer:
    """LPIPS of rendered images against their targets (``__call__``), on the images' device in float32 (autocast
    off: a mixed-precision evaluation still scores in float32), without gradients. A plain object rather
    than a module, so that it is no part of the model: not in its checkpoints, not trained, not wrapped
    by DDP; its network moves to an image's device when one first arrives there. ``metric``: the name its scores
    are recorded under, from the digest of the weights its network loaded (``weights_sha256``): ``lpips``
    (``PUBLISHED``) for torchvision's (``ALEXNET_SHA256``), ``lpips_custom`` (``CUSTOM``) for any other."""

    def __init__(self, network: LpipsNetwork):
        self.network = network.eval()
        self.weights_sha256 = network.weights_sha256
        self.metric = PUBLISHED if network.weights_sha256 == ALEXNET_SHA256 else CUSTOM

    def __call__(self, image: Tensor, target: Tensor) -> float:
        """LPIPS of ``image`` against ``target``, [H, W, 3] in [0, 1] each (``lpips_input``); an
        ``ImageTooSmall`` where a side is below ``MIN_SIDE``."""
        H, W, _ = image.shape
        if min(H, W) < MIN_SIDE:
            raise ImageTooSmall(f"LPIPS needs images of at least {MIN_SIDE} x {MIN_SIDE} pixels (AlexNet's strides "
                                f"and pools), these are {W} x {H}")
        if self.network.shift.device != image.device:
            self.network.to(image.device)
        with torch.no_grad(), torch.autocast(image.device.type, enabled=False):
            return float(self.network(lpips_input(image), lpips_input(target))[0])


def lpips_scorer(setting: bool | str, weights: str | Path | None,
                 custom: bool = False) -> tuple[LpipsScorer | None, str]:
    """The scorer ``model.lpips`` (``setting``: auto, true or false), ``model.lpips_weights`` (``weights``) and
    ``model.lpips_custom`` (``custom``) ask for, and a line saying why there is none where auto has no weights
    (else ""). Weights missing from the hub cache are downloaded there first (``fetch_alexnet``, from
    ``ALEXNET_URL``); a file the config names is never downloaded. Under auto without a file named, weights that
    cannot be had from the hub cache (not downloaded there: no network, ``TORCH_HOME`` a file, a cache folder it
    may not write, a download whose digest is not theirs; or there and unreadable) are "LPIPS not scored: why",
    the line naming the real file or folder (``not_scored``). No weights at a path the config names, none to be had
    under true, a file whose SHA-256 is not ``ALEXNET_SHA256`` without ``custom``, or a file that is not AlexNet's
    weights at all, is a ConfigError (``check_weights_file``, ``lpips_network``), under auto too. The file's
    digest is taken again of the bytes loaded: a file changed since the settings were checked is refused as
    well."""
    if setting is False:
        return None, ""
    check_weights_file(setting, weights, custom)
    path = weights_file(weights)
    hub_under_auto = setting == "auto" and weights is None  # what auto may do without, with a line
    if not os.path.isfile(path):  # only auto reading the hub cache gets here without the file
        try:
            path = fetch_alexnet(path.parent)
        except DownloadFailed as error:
            return None, not_scored(f"no AlexNet ImageNet weights at {path}, and downloading them failed ({error})")
    try:
        return LpipsScorer(lpips_network(path, None if custom else ALEXNET_SHA256)), ""
    except UnreadableWeights as error:
        if not hub_under_auto:
            raise
        return None, not_scored(str(error))


def not_scored(why: str) -> str:
    """The line that says LPIPS is not scored under ``model.lpips=auto``, ``why``, and what to do."""
    return (f"LPIPS not scored: {why}: put {ALEXNET_URL} there or set model.lpips_weights=FILE; model.lpips=false "
            "turns LPIPS off (docs/metrics.md)")


def check_weights_file(setting: bool | str, weights: str | Path | None, custom: bool = False) -> None:
    """A ConfigError where LPIPS must be scored from a file that is not there, or is not the one nerfexp can
    vouch for: ``model.lpips_custom`` (``custom``) without a file named; the file ``model.lpips_weights`` names
    (``weights``) missing; a file, named or in the hub cache, whose SHA-256 is not ``ALEXNET_SHA256`` (``mismatch``),
    unless ``custom`` says it is the user's own on purpose (then one not of AlexNet's keys and shapes,
    ``backbone_state``); or under ``model.lpips=true`` no file in the hub cache
    and downloading it there (``fetch_alexnet``, once, before any work) failing, or the file there unreadable
    (``UnreadableWeights``). Nothing to check under false, or under auto where the hub cache lacks the file or it
    cannot be read (``lpips_scorer`` downloads it when LPIPS is set up, or says why not)."""
    if setting is False:
        return
    if custom and weights is None:
        raise ConfigError("model.lpips_custom=true says the AlexNet weights model.lpips_weights names are your own, "
                          "and it names none: set model.lpips_weights=FILE, or drop model.lpips_custom "
                          "(docs/metrics.md)")
    path = weights_file(weights)
    if os.path.isfile(path):
        try:
            data, found = weights_bytes(path)
        except UnreadableWeights:
            if setting == "auto" and weights is None:  # the hub cache's, unreadable: lpips_scorer says so
                return
            raise
        if not custom and found != ALEXNET_SHA256:
            raise ConfigError(mismatch(path, found))
        if custom:  # any digest, so its keys and shapes are checked now (the published digest vouches for them)
            backbone_state(path, data)
        return
    if weights is not None:
        raise ConfigError(f"model.lpips_weights={weights}: no such file; expected torchvision's AlexNet ImageNet "
                          f"weights ({ALEXNET_FILE}) there (docs/metrics.md)")
    if setting == "auto":
        return
    try:
        fetch_alexnet(path.parent)
    except DownloadFailed as error:
        raise ConfigError(f"model.lpips=true: no AlexNet ImageNet weights at {path}, and downloading them failed "
                          f"({error}): put {ALEXNET_URL} there or set model.lpips_weights=FILE "
                          "(docs/metrics.md)") from None
