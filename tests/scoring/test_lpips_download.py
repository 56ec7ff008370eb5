"""AlexNet's weights downloaded into the torch hub cache where they are missing
(nerfexp.scoring.perceptual.fetch_alexnet, and lpips_scorer and check_weights_file, which call it), from a
server on 127.0.0.1 (tests/scoring/weights_server.py): no test reaches the internet. A file's name carries the
first hex digits of its SHA-256, as torch hub's does (``name-<hex>.ext``), and the whole digest is nerfexp's
(``ALEXNET_SHA256``), so each test names what it serves by the SHA-256 of its bytes and gives that digest. However a
download fails, the cache is left without the file and without a temporary one."""

import contextlib
import hashlib
import io
import json
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from urllib.error import HTTPError, URLError

import pytest
import torch

from nerfexp.errors import ConfigError
from nerfexp.scoring import perceptual
from nerfexp.scoring.perceptual import (
    ALEXNET_FILE,
    ALEXNET_URL,
    DownloadFailed,
    LpipsScorer,
    check_weights_file,
    download_failure,
    fetch_alexnet,
    hub_weights_file,
    lpips_network,
    lpips_scorer,
    url_file_name,
)
from tests.helpers import immutable, one_error_line, run_nerfexp
from tests.scoring.alexnet import alexnet_state
from tests.scoring.weights_server import Cut, hashed_name, misnamed, refused_url, serving, silent


def digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()

DATA = bytes(range(256)) * 64  # a small stand-in for a weights file: 16 kB


def files_in(directory: Path) -> list[str]:
    return sorted(path.name for path in directory.iterdir()) if directory.exists() else []


def alexnet_bytes() -> bytes:
    buffer = io.BytesIO()
    torch.save(alexnet_state(), buffer)
    return buffer.getvalue()


def image_pair() -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(0)
    image = torch.rand(40, 48, 3, generator=generator)
    return image, (image + 0.1 * torch.rand(40, 48, 3, generator=generator)).clamp(0, 1)


def test_the_published_address_names_the_file_the_hub_cache_keeps():
    assert url_file_name(ALEXNET_URL) == ALEXNET_FILE
    assert ALEXNET_URL == f"https://download.pytorch.org/models/{ALEXNET_FILE}"  # torchvision's AlexNet_Weights
    assert torch.hub.HASH_REGEX.search(ALEXNET_FILE).group(1) == "7be5be79"


def test_a_file_is_downloaded_under_its_name_once_its_hash_matches(tmp_path):
    name = hashed_name("weights", DATA)
    cache = tmp_path / "hub" / "checkpoints"  # made by the download
    with serving({name: DATA}) as server:
        path = fetch_alexnet(cache, server.url(name), digest(DATA))
    assert path == cache / name and path.read_bytes() == DATA
    assert files_in(cache) == [name] and server.requests == [name]  # no temporary file left


@pytest.mark.parametrize("case, reason", [
    ("wrong hash", r"SHA-256 check failed"),
    ("body cut short", r"SHA-256 check failed: a truncated or altered download"),  # urllib stops at the cut
    ("no such file", r"HTTP 404 Not Found"),
    ("connection refused", r"Connection refused"),
])
def test_a_failed_download_leaves_the_cache_without_the_file_and_says_why(tmp_path, case, reason):
    cache = tmp_path / "checkpoints"
    name = hashed_name("weights", DATA)
    files = {"wrong hash": {name: DATA[::-1]}, "body cut short": {name: Cut(DATA, len(DATA) // 3)},
             "no such file": {}, "connection refused": {}}[case]
    with serving(files) as server:
        url = refused_url(name) if case == "connection refused" else server.url(name)
        with pytest.raises(DownloadFailed, match=f"^{reason}") as error:
            fetch_alexnet(cache, url, digest(DATA))
    assert "\n" not in str(error.value)
    assert server.requests == ([] if case == "connection refused" else [name])
    assert files_in(cache) == []  # neither the name nor a temporary file


def test_a_name_without_a_hash_is_refused_before_any_request(tmp_path):
    with serving({"weights.pth": DATA}) as server:
        with pytest.raises(ValueError, match="carries no hash"):
            fetch_alexnet(tmp_path, server.url("weights.pth"))
        with pytest.raises(ValueError, match="carries no hash"):
            fetch_alexnet(tmp_path, server.url("weights-.pth"))  # HASH_REGEX's empty match would check nothing
    assert server.requests == [] and files_in(tmp_path) == []


def test_a_file_whose_whole_digest_differs_past_the_names_digits_never_takes_the_name(tmp_path):
    # the 8 hex digits of a name are 32 bits, which a forger can match: the whole SHA-256 decides
    cache, name = tmp_path / "checkpoints", hashed_name("weights", DATA)
    expected = digest(DATA)[:8] + "0" * 56  # the name's digits, another digest
    with serving({name: DATA}) as server:
        with pytest.raises(DownloadFailed) as error:
            fetch_alexnet(cache, server.url(name), expected)
    assert str(error.value) == f"SHA-256 check failed: {digest(DATA)}, expected {expected}"
    assert server.requests == [name] and files_in(cache) == []  # neither the name nor a temporary file


def test_a_name_whose_digits_do_not_begin_the_digest_is_refused_before_any_request(tmp_path):
    name = misnamed("weights", DATA)
    with serving({name: DATA}) as server:
        with pytest.raises(ValueError, match=f"its file name's hash {name[8:16]} does not begin the SHA-256"):
            fetch_alexnet(tmp_path, server.url(name), digest(DATA))
    assert server.requests == [] and files_in(tmp_path) == []


def test_a_server_that_never_answers_is_given_up_on_after_the_timeout(tmp_path, monkeypatch):
    monkeypatch.setattr(perceptual, "TIMEOUT_S", 0.5)
    name = hashed_name("weights", DATA)
    before = socket.getdefaulttimeout()
    with silent() as folder:
        started = time.monotonic()
        with pytest.raises(DownloadFailed, match="^timed out$"):
            fetch_alexnet(tmp_path / "checkpoints", f"{folder}/{name}", digest(DATA))
        waited = time.monotonic() - started
    assert 0.5 <= waited < 10  # the timeout's, not the system's minutes
    assert socket.getdefaulttimeout() == before and files_in(tmp_path / "checkpoints") == []


@pytest.mark.parametrize("seconds", [0.25, 3.0])
def test_the_timeout_holds_only_within_its_block_and_is_put_back_after_an_error(seconds):
    before = socket.getdefaulttimeout()
    with pytest.raises(KeyError):
        with perceptual.socket_timeout(seconds):
            assert socket.getdefaulttimeout() == seconds
            raise KeyError("any failure")
    assert socket.getdefaulttimeout() == before


@pytest.mark.parametrize("error, why", [
    (URLError(socket.gaierror(-2, "Name or service not known")), "name lookup failed: Name or service not known"),
    (URLError(ConnectionRefusedError(111, "Connection refused")), "Connection refused"),
    (URLError(OSError(101, "Network is unreachable")), "Network is unreachable"),
    (HTTPError("http://x/a-1.pth", 403, "Forbidden", None, None), "HTTP 403 Forbidden"),
    (RuntimeError('invalid hash value (expected "7be5be79", got "00")'),
     "SHA-256 check failed: a truncated or altered download"),
    (TimeoutError("timed out"), "timed out"),
    (OSError(28, "No space left on device"), "No space left on device"),
])
def test_why_a_download_failed_is_said_in_a_few_words(error, why):
    assert download_failure(error) == why


@pytest.fixture
def empty_hub(tmp_path, monkeypatch) -> Path:
    """An empty torch hub cache in ``tmp_path``; its checkpoints folder."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    return tmp_path / "torch" / "hub" / "checkpoints"


def publish(monkeypatch, url: str, data: bytes) -> None:
    """Make ``data`` at ``url`` stand in for torchvision's published weights: nerfexp's address and digest."""
    monkeypatch.setattr(perceptual, "ALEXNET_URL", url)
    monkeypatch.setattr(perceptual, "ALEXNET_SHA256", digest(data))


def test_auto_downloads_the_weights_once_and_scores_with_them(empty_hub, tmp_path, monkeypatch):
    data = alexnet_bytes()
    name = hashed_name("alexnet-owt", data)
    (tmp_path / "own.pth").write_bytes(data)
    with serving({name: data}) as server:
        publish(monkeypatch, server.url(name), data)
        assert hub_weights_file() == empty_hub / name
        scorer, line = lpips_scorer("auto", None)
        assert isinstance(scorer, LpipsScorer) and line == ""
        assert files_in(empty_hub) == [name] and (empty_hub / name).read_bytes() == data
        for setting in ("auto", True):  # found in the cache: not downloaded again
            again, _ = lpips_scorer(setting, None)
            assert isinstance(again, LpipsScorer)
    assert server.requests == [name]
    image, target = image_pair()
    assert scorer(image, target) == LpipsScorer(lpips_network(tmp_path / "own.pth"))(image, target) > 0


def test_true_downloads_the_weights_when_checked_before_any_work(empty_hub, monkeypatch):
    name = hashed_name("alexnet-owt", DATA)
    with serving({name: DATA}) as server:
        publish(monkeypatch, server.url(name), DATA)
        check_weights_file(True, None)
        check_weights_file(True, None)
    assert server.requests == [name] and files_in(empty_hub) == [name]


@pytest.mark.parametrize("case, reason", [("wrong hash", "SHA-256 check failed"),
                                          ("connection refused", "Connection refused")])
def test_a_failed_download_is_one_line_under_auto_and_an_error_under_true(empty_hub, monkeypatch, case, reason):
    data = alexnet_bytes()
    name = hashed_name("alexnet-owt", data)
    with serving({name: data[::-1] if case == "wrong hash" else data}) as server:
        url = refused_url(name) if case == "connection refused" else server.url(name)
        publish(monkeypatch, url, data)
        none, line = lpips_scorer("auto", None)
        with pytest.raises(ConfigError) as error:
            lpips_scorer(True, None)
    assert none is None and "\n" not in line and "\n" not in str(error.value)
    assert line.startswith(f"LPIPS not scored: no AlexNet ImageNet weights at {empty_hub / name}, and downloading "
                           f"them failed ({reason}")
    assert f"put {url} there or set model.lpips_weights=FILE; model.lpips=false turns LPIPS off" in line
    assert str(error.value).startswith(f"model.lpips=true: no AlexNet ImageNet weights at {empty_hub / name}, and "
                                       f"downloading them failed ({reason}")
    assert files_in(empty_hub) == []


def test_nothing_is_downloaded_where_the_config_names_a_file_or_turns_lpips_off(empty_hub, tmp_path, monkeypatch):
    data = alexnet_bytes()
    name = hashed_name("alexnet-owt", data)
    (tmp_path / "own.pth").write_bytes(data)
    with serving({name: data}) as server:
        publish(monkeypatch, server.url(name), data)
        with pytest.raises(ConfigError, match="^model.lpips_weights=/no/such.pth: no such file"):
            lpips_scorer("auto", "/no/such.pth")
        with pytest.raises(ConfigError, match="^model.lpips_weights=/no/such.pth: no such file"):
            check_weights_file(True, "/no/such.pth")
        for setting in ("auto", True):
            named, _ = lpips_scorer(setting, str(tmp_path / "own.pth"))
            assert isinstance(named, LpipsScorer)
        assert lpips_scorer(False, None) == (None, "")
        check_weights_file("auto", None)  # auto downloads when LPIPS is set up, not when the config is checked
    assert server.requests == [] and files_in(empty_hub) == []


# Each way the hub cache may fail to give AlexNet's weights (the issue's: TORCH_HOME a file, which stopped a default
# run with a line naming a temporary ``.unchecked`` file), as (what goes wrong, what the line says of it): under
# auto LPIPS is not scored, with one line naming the real file or folder; under true it is an error in those words
HUB_FAILURES = ["TORCH_HOME a file", "cache folder not writable", "no network", "wrong digest", "file unreadable"]


@contextlib.contextmanager
def failing_hub(case: str, root: Path, monkeypatch) -> Iterator[tuple[Path, str]]:
    """A torch hub cache under ``root`` (``TORCH_HOME``) from which AlexNet's weights cannot be had as ``case``
    says, served (where served at all) from 127.0.0.1: (the cache's checkpoints folder, why a line must say)."""
    data = alexnet_bytes()
    name = hashed_name("alexnet-owt", data)
    home = root / "torch"
    checkpoints = home / "hub" / "checkpoints"
    with serving({name: data[::-1] if case == "wrong digest" else data}) as server:
        publish(monkeypatch, refused_url(name) if case == "no network" else server.url(name), data)
        monkeypatch.setenv("TORCH_HOME", str(home))
        if case == "TORCH_HOME a file":
            home.write_text("not a folder")
            yield checkpoints, f"({home} is not a folder)"
        elif case == "cache folder not writable":
            checkpoints.mkdir(parents=True)
            with immutable(checkpoints):  # as root, a mode stops no write
                yield checkpoints, f"(cannot write {checkpoints / name} (Operation not permitted))"
        elif case == "file unreadable":
            checkpoints.mkdir(parents=True)
            (checkpoints / name).write_bytes(data)
            monkeypatch.setattr(perceptual, "WEIGHTS_BYTES", 1000)  # as root, a mode stops no read: too large instead
            yield checkpoints, f"{checkpoints / name}: larger than the 1,000 bytes nerfexp reads of such a file"
        else:
            yield checkpoints, {"no network": "(Connection refused)", "wrong digest": "(SHA-256 check failed"}[case]


@pytest.mark.parametrize("case", HUB_FAILURES)
def test_auto_without_the_hub_caches_weights_is_one_line_naming_the_real_place_and_true_refuses(tmp_path, monkeypatch,
                                                                                                case):
    with failing_hub(case, tmp_path, monkeypatch) as (checkpoints, why):
        check_weights_file("auto", None)  # auto: nothing refused before any work
        none, line = lpips_scorer("auto", None)
        for check in (check_weights_file, lpips_scorer):
            with pytest.raises(ConfigError) as error:
                check(True, None)
            refusal = str(error.value)
            assert why in refusal and "\n" not in refusal and ".unchecked" not in refusal, refusal
            assert ".partial" not in refusal
        left = files_in(checkpoints)
    assert none is None and line.startswith("LPIPS not scored: ") and why in line, line
    assert "\n" not in line and ".unchecked" not in line and ".partial" not in line
    assert line.endswith("model.lpips=false turns LPIPS off (docs/metrics.md)")
    assert not [name for name in left if name.endswith((".unchecked", ".partial"))]  # no temporary file left


@pytest.mark.parametrize("lpips", ["auto", "true"])
def test_a_default_run_with_torch_home_a_file_trains_without_lpips_and_true_stops_in_one_line(tmp_path, tiny,
                                                                                              monkeypatch, lpips):
    # the case, on the command line: TORCH_HOME pointing at a file
    home = tmp_path / "torch_home"
    home.write_text("not a folder")
    monkeypatch.setenv("TORCH_HOME", str(home))
    run_dir = tmp_path / "run"
    result = run_nerfexp(*tiny, "scale.steps=2", "scale.val_every=2", "test_budgets=[]", f"model.lpips={lpips}",
                         f"hydra.run.dir={run_dir}", cwd=tmp_path)
    weights = home / "hub" / "checkpoints" / ALEXNET_FILE
    if lpips == "auto":
        assert result.returncode == 0, result.stderr[-3000:]
        assert (f"LPIPS not scored: no AlexNet ImageNet weights at {weights}, and downloading them failed ({home} is "
                "not a folder)") in result.stdout
        assert "test_lpips" not in json.loads((run_dir / "results.json").read_text())
    else:
        line = one_error_line(result)
        assert line.startswith(f"nerfexp: error: model.lpips=true: no AlexNet ImageNet weights at {weights}, and "
                               f"downloading them failed ({home} is not a folder): put ")
        assert not run_dir.exists()
    assert ".unchecked" not in result.stdout + result.stderr
