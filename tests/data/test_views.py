"""When two views are the same view (``nerfexp.data.views``): one file under any spelling or link, or the same
pixels and pose; no training view among the validation or test views, no view twice in a split, and validation
views that are test views allowed."""

import os
import re

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from nerfexp.data.procedural import load_procedural
from nerfexp.data.views import Source, Views, check_distinct_views, check_shared_file, holdout_split
from nerfexp.errors import DatasetError
from nerfexp.pixels import png_bytes

POOL = load_procedural("train", 6, 8, 8, supersample=1)  # six distinct views (each its own pose)
SPLITS = ("train", "val", "test")


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
            check_distinct_views(splits)
    else:
        check_distinct_views(splits)


def test_the_message_names_both_views_and_the_score_it_would_spoil():
    splits = {"train": POOL.subset(torch.tensor([0, 1, 2])), "val": POOL.subset(torch.tensor([4])),
              "test": POOL.subset(torch.tensor([4, 2]))}
    with pytest.raises(DatasetError) as error:
        check_distinct_views(splits)
    assert str(error.value) == ("the test view 1 and the training view 2 are one view (they have the same pixels and "
                                "the same pose): a score on views training saw is no test score; keep it in one split")


def test_the_same_pixels_under_another_pose_are_another_view():
    moved = POOL.subset(torch.tensor([0]))
    moved.c2w = moved.c2w.clone()
    moved.c2w[0, 0, 3] += 1e-3  # the same image, a camera a thousandth of a unit aside
    check_distinct_views({"train": POOL.subset(torch.tensor([0, 1])), "val": moved, "test": moved})


def test_holdout_splits_share_only_validation_with_test():
    # every holdout-th image a test view, validation the first test views: the convention the check allows
    views = load_procedural("train", 17, 8, 8, supersample=1)
    splits = holdout_split(17, 8, n_val=2)
    assert set(splits["val"].tolist()) <= set(splits["test"].tolist())
    check_distinct_views({split: views.subset(index) for split, index in splits.items()})


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
        check_distinct_views({"train": train, "val": POOL.subset(torch.tensor([5])), "test": test})


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
