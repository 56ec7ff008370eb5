"""When two views are the same view (``nerfexp.data.views``): one file under any spelling or link, or, across
splits, cameras that nearly coincide and images that nearly match (within a split the same pixels and pose); no
training view among the validation or test views, no view twice in a split, and validation views that are test
views allowed."""

import math
import os
import re

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from nerfexp.data import views
from nerfexp.data.procedural import load_procedural
from nerfexp.data.views import (
    CENTRE_FRACTION,
    IMAGE_PSNR_DB,
    RAY_DEGREES,
    Source,
    Views,
    check_distinct_views,
    check_shared_file,
    holdout_split,
)
from nerfexp.errors import DatasetError
from nerfexp.geometry.lenses import Intrinsics
from nerfexp.pixels import png_bytes

POOL = load_procedural("train", 6, 8, 8, supersample=1)  # six distinct views (each its own pose)
SPLITS = ("train", "val", "test")
WHITE = torch.ones(3)  # the background the images are scored over


def expected_clash(chosen: dict[str, list[int]]) -> bool:
    """Whether splits of the pool's views ``chosen`` (indices per split) hold one view twice or a training view
    among the validation or test views: worked out from the indices alone."""
    twice = any(len(set(index)) < len(index) for index in chosen.values())
    trained = set(chosen["train"])
    return twice or bool(trained & set(chosen["val"])) or bool(trained & set(chosen["test"]))


@settings(max_examples=60, deadline=None)
@given(st.fixed_dictionaries({split: st.lists(st.integers(0, len(POOL) - 1), min_size=1, max_size=4)
                              for split in SPLITS}))
def test_splits_are_refused_exactly_where_a_view_is_shared_that_may_not_be(chosen):
    splits = {split: POOL.subset(torch.tensor(index)) for split, index in chosen.items()}
    if expected_clash(chosen):
        with pytest.raises(DatasetError, match=r"^the \w+ view \d+ and the \w+ view \d+ are one view \(they have "
                                               r"the same pixels and the same pose\)"):
            check_distinct_views(splits, WHITE)
    else:
        check_distinct_views(splits, WHITE)


def test_the_message_names_both_views_and_the_score_it_would_spoil():
    splits = {"train": POOL.subset(torch.tensor([0, 1, 2])), "val": POOL.subset(torch.tensor([4])),
              "test": POOL.subset(torch.tensor([4, 2]))}
    with pytest.raises(DatasetError) as error:
        check_distinct_views(splits, WHITE)
    assert str(error.value) == ("the test view 1 and the training view 2 are one view (they have the same pixels and "
                                "the same pose): a score on views training saw is no test score; keep it in one split")


SIDE, FOCAL = 8, 10.0  # the hand-made views: 8 x 8 pixels, a pinhole of focal length 10 pixels
IMAGES = 0.2 + 0.6 * torch.rand(3, SIDE, SIDE, 3, generator=torch.Generator().manual_seed(0))  # opaque, no clipping


def yawed(degrees: float) -> torch.Tensor:
    """The rotation [3, 3] by ``degrees`` about the world's y axis (a camera looking down -z turned sideways)."""
    a = math.radians(degrees)
    return torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]],
                        dtype=torch.float64)


def posed(centre, image: torch.Tensor, degrees: float = 0.0, focal: float = FOCAL) -> Views:
    """One opaque view of ``image`` [H, W, 3] from a camera at ``centre`` looking down -z, turned by ``degrees``
    about y, through a centred pinhole of ``focal`` pixels."""
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3], c2w[:3, 3] = yawed(degrees), torch.tensor(centre, dtype=torch.float64)
    H, W, _ = image.shape
    return Views(torch.cat([image, torch.ones(H, W, 1)], -1)[None], c2w.float()[None],
                 Intrinsics.pinhole(focal, H, W, (1,)))


def joined(*views: Views) -> Views:
    return Views(torch.cat([v.rgba for v in views]), torch.cat([v.c2w for v in views]),
                 Intrinsics.stack([v.intrinsics[0] for v in views]))


# Training views at (-1, 0, 0) and (1, 0, 0); the validation and the test split each hold a copy of the first,
# moved by d along y: the centres' mean is (-1/2, d/2, 0) and their squared distances from it 1/4 + d^2/4 (three
# of them) and 9/4 + d^2/4, so the spread is sqrt(3/4 + d^2/4) = sqrt(3 + d^2) / 2, about 0.8660: the copy is one
# view within 0.01 x 0.8660 = 0.00866. Its rays are those of the first turned by its yaw (the image's centre ray
# turns by all of it), or through a lens of another focal length (a corner ray 3.5 sqrt(2) pixels from the centre
# turns by atan(3.5 sqrt(2) / f) - atan(3.5 sqrt(2) / f')); its image brighter by b has the PSNR -20 log10(b).
CORNER = 3.5 * math.sqrt(2)


def corner_degrees(scale: float) -> float:
    return math.degrees(math.atan(CORNER / FOCAL) - math.atan(CORNER / (FOCAL * scale)))


@pytest.mark.parametrize(("change", "likeness"), [
    ({"moved": 0.0085}, f"their cameras {0.0085 / (math.sqrt(3 + 0.0085 ** 2) / 2):.2g} of the cameras' spread and 0 "
                        "degrees apart, their images identical"),
    ({"moved": 0.0088}, None),  # 0.0102 of the spread
    ({"degrees": 0.45}, "their cameras 0 of the cameras' spread and 0.45 degrees apart, their images identical"),
    ({"degrees": 0.55}, None),
    ({"focal": 1.02}, f"their cameras 0 of the cameras' spread and {corner_degrees(1.02):.2g} degrees apart, their "
                      "images identical"),
    ({"focal": 1.025}, None),  # 0.57 degrees at the corners
    ({"brighter": 0.099}, f"their cameras 0 of the cameras' spread and 0 degrees apart, their images at "
                          f"{-20 * math.log10(0.099):.1f} dB PSNR"),
    ({"brighter": 0.101}, None),  # 19.9 dB
], ids=lambda value: str(value)[:24])
def test_a_view_is_one_with_a_training_view_within_each_tolerance_and_another_beyond_it(change, likeness):
    copy = posed((-1.0, change.get("moved", 0.0), 0.0), IMAGES[0] + change.get("brighter", 0.0),
                 change.get("degrees", 0.0), FOCAL * change.get("focal", 1.0))
    splits = {"train": joined(posed((-1.0, 0.0, 0.0), IMAGES[0]), posed((1.0, 0.0, 0.0), IMAGES[1])),
              "val": copy, "test": copy}
    if likeness is None:
        record = check_distinct_views(splits, WHITE)
        assert record["centre_spread"] == pytest.approx(math.sqrt(3 + change.get("moved", 0.0) ** 2) / 2, rel=1e-6)
        # the cameras matched (and the images were compared) only where the image alone differs
        assert record["image_pairs"] == (2 if "brighter" in change else 0)
    else:
        with pytest.raises(DatasetError) as caught:
            check_distinct_views(splits, WHITE)
        assert str(caught.value) == (
            f"the validation view 0 and the training view 0 are one view ({likeness}: one view is cameras within 0.01 "
            "of the spread and 0.5 degrees, images at 20 dB or more): a score on views training saw is no validation "
            "score; keep it in one split")


@pytest.mark.parametrize(("degrees", "image", "clash"), [(0.0, 0, True), (10.0, 0, False), (0.0, 2, False)])
def test_cameras_at_one_point_are_told_apart_by_direction_and_image(degrees, image, clash):
    # no spread: every centre within 0.01 x 0 of the others, so the rays and the images decide
    copy = posed((0.0, 0.0, 0.0), IMAGES[image], degrees)
    splits = {"train": joined(posed((0.0, 0.0, 0.0), IMAGES[0]), posed((0.0, 0.0, 0.0), IMAGES[1], 90.0)),
              "val": copy, "test": copy}
    if clash:
        with pytest.raises(DatasetError, match=re.escape("are one view (they have the same pixels and the same pose)")):
            check_distinct_views(splits, WHITE)
    else:
        record = check_distinct_views(splits, WHITE)
        assert record["centre_spread"] == 0 and record["image_pairs"] == (2 if degrees == 0 else 0)


def test_within_a_split_only_an_exact_copy_is_one_view():
    # a camera that paused in a video: a near copy in one split weighs its view a little more, scores nothing seen
    near = joined(posed((-1.0, 0.0, 0.0), IMAGES[0]), posed((-1.0, 0.001, 0.0), IMAGES[0]),
                  posed((1.0, 0.0, 0.0), IMAGES[1]))
    others = {"val": posed((0.0, 2.0, 0.0), IMAGES[2]), "test": posed((0.0, 2.0, 0.0), IMAGES[2])}
    assert check_distinct_views({"train": near, **others}, WHITE)["image_pairs"] == 0
    exact = joined(posed((-1.0, 0.0, 0.0), IMAGES[0]), posed((1.0, 0.0, 0.0), IMAGES[1]),
                   posed((-1.0, 0.0, 0.0), IMAGES[0]))
    with pytest.raises(DatasetError, match=r"^the training view 2 and the training view 0 are one view \(they have the "
                                           r"same pixels and the same pose\): a split holds each view once$"):
        check_distinct_views({"train": exact, **others}, WHITE)


def test_images_of_another_size_are_another_view():
    # the training image at half its size, its lens following: not compared pixel by pixel, so not refused
    train = joined(posed((-1.0, 0.0, 0.0), IMAGES[0]), posed((1.0, 0.0, 0.0), IMAGES[1]))
    half = train.subset(torch.tensor([0])).resized(torch.nn.functional.avg_pool2d(
        train.rgba[:1].permute(0, 3, 1, 2), 2).permute(0, 2, 3, 1))
    assert check_distinct_views({"train": train, "val": half, "test": half}, WHITE)["image_pairs"] == 0


def test_the_record_says_the_tolerances_and_the_spread_of_every_camera():
    splits = {"train": POOL.subset(torch.tensor([0, 1, 2])), "val": POOL.subset(torch.tensor([3])),
              "test": POOL.subset(torch.tensor([3, 4]))}
    centres = torch.cat([views.c2w[:, :3, 3] for views in splits.values()]).double().numpy()
    spread = float(np.sqrt(np.mean(np.sum((centres - centres.mean(0)) ** 2, -1))))  # NumPy, apart from torch's
    assert check_distinct_views(splits, WHITE) == {
        "centre_fraction": CENTRE_FRACTION, "centre_spread": pytest.approx(spread, rel=1e-12),
        "ray_degrees": RAY_DEGREES, "image_psnr_db": IMAGE_PSNR_DB, "views": 6, "image_pairs": 0}


def random_cameras(n: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Centres [n, 3] and unit rays [n, 5, 3] drawn at random: cameras that match none but by chance."""
    centres = torch.randn(n, 3, dtype=torch.float64, generator=generator)
    rays = torch.nn.functional.normalize(torch.randn(n, 5, 3, dtype=torch.float64, generator=generator), dim=-1)
    return centres, rays


@pytest.mark.parametrize("block", [1, 7, 300])
def test_cameras_are_matched_alike_in_blocks_of_any_size(monkeypatch, block):
    # 400 cameras against 300, the first 30 near copies of every tenth: blocks of rows find the pairs that one
    # matrix of every pair finds
    g = torch.Generator().manual_seed(1)
    centres, rays = random_cameras(300, g)
    others = random_cameras(370, g)
    near = torch.arange(0, 300, 10)
    a = torch.cat([centres[near] + 1e-4, others[0]]), torch.cat([rays[near], others[1]])
    whole = views.camera_matches(a, (centres, rays), 0.01)
    monkeypatch.setattr(views, "PAIRS_PER_BLOCK", block * 300)
    assert views.camera_matches(a, (centres, rays), 0.01) == whole
    assert whole == [(i, k) for i, k in enumerate(near.tolist())]


def test_exact_copies_within_a_split_are_found_in_one_pass():
    # ten thousand views, each pose twice: the pairs, found by grouping the poses, not by comparing every pair
    c2w = torch.eye(4).repeat(5000, 1, 1)
    c2w[:, :3, 3] = torch.randn(5000, 3, generator=torch.Generator().manual_seed(2))
    twice = Views(torch.zeros(10000, 1, 1, 4), torch.cat([c2w, c2w]), Intrinsics.pinhole(1.0, 1, 1, (10000,)))
    assert views.same_cameras(twice) == [(5000 + i, i) for i in range(5000)]


def test_holdout_splits_share_only_validation_with_test():
    # every holdout-th image a test view, validation the first test views: the convention the check allows
    views = load_procedural("train", 17, 8, 8, supersample=1)
    splits = holdout_split(17, 8, n_val=2)
    assert set(splits["val"].tolist()) <= set(splits["test"].tolist())
    check_distinct_views({split: views.subset(index) for split, index in splits.items()}, WHITE)


def write_images(folder, n: int) -> list:
    folder.mkdir()
    paths = [folder / f"{i}.png" for i in range(n)]
    for path, image in zip(paths, (POOL.rgba[:n] * 255).round().byte()):
        path.write_bytes(png_bytes(image.numpy()))
    return paths


@pytest.mark.parametrize("spelling", ["images//0.png", "images/./0.png", "./images/0.png", "link", "hard link"])
def test_one_file_under_any_spelling_or_link_is_one_view(tmp_path, spelling):
    write_images(tmp_path / "images", 2)
    if spelling == "link":
        os.symlink("0.png", tmp_path / "images" / "link.png")
        spelling = "images/link.png"
    elif spelling == "hard link":
        os.link(tmp_path / "images" / "0.png", tmp_path / "images" / "hard.png")
        spelling = "images/hard.png"
    sources = [Source("frame 0", tmp_path / "images/0.png"), Source("frame 1", tmp_path / "images/1.png"),
               Source(f"frame 2 ({spelling})", tmp_path / spelling)]
    with pytest.raises(DatasetError, match=re.escape(f"frame 0 and frame 2 ({spelling}) name one file")):
        check_shared_file(sources)
    check_shared_file(sources[:2])  # two files: two views
    # across splits, read from the files: another pose and other pixels (a render's noise) do not hide it
    train = Views(POOL.rgba[:2], POOL.c2w[:2], POOL.intrinsics[:2], sources=tuple(sources[:2]))
    test = Views(POOL.rgba[3:4], POOL.c2w[3:4], POOL.intrinsics[3:4], sources=(sources[2],))
    with pytest.raises(DatasetError, match=re.escape(f"the test view frame 2 ({spelling}) and the training view "
                                                     "frame 0 are one view (they name one file")):
        check_distinct_views({"train": train, "val": POOL.subset(torch.tensor([5])), "test": test}, WHITE)


def test_a_missing_file_is_left_to_its_reader(tmp_path):
    missing = [Source("frame 0", tmp_path / "gone.png"), Source("frame 1", tmp_path / "also_gone.png")]
    check_shared_file(missing)  # read_image names the missing file when it is read


def test_subsets_and_resizing_keep_each_views_source(tmp_path):
    sources = tuple(Source(f"frame {i}", tmp_path / f"{i}.png") for i in range(len(POOL)))
    views = Views(POOL.rgba, POOL.c2w, POOL.intrinsics, sources=sources)
    assert views.subset(torch.tensor([4, 1])).sources == (sources[4], sources[1])
    assert views.subset(torch.arange(len(POOL)) % 2 == 1).sources == sources[1::2]
    assert views.resized(POOL.rgba[:, ::2, ::2]).sources == sources
    assert [views.name(i) for i in (0, 5)] == ["frame 0", "frame 5"] and POOL.name(5) == "5"
