"""nerfstudio's format (``data=nerfstudio``): scenes written by nerfexp read back to the same rays, Instant-NGP's
variant, downscaled folders, masks, splits, and one line naming the file, the frame and the key for every
malformed field."""

import json
import math
import os
import shutil

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from nerfexp.data.datamodule import RayDataModule
from nerfexp.data.nerfstudio import NerfstudioScene
from nerfexp.data.procedural import load_procedural, occlude, real_lens
from nerfexp.data.rays import RandomRays, WholeImages
from nerfexp.data.transforms_file import TRANSFORMS, scene_file, spelling, write_nerfstudio
from nerfexp.data.views import Views
from nerfexp.errors import DatasetError
from nerfexp.geometry.cameras import focal_from_fov
from nerfexp.geometry.lenses import Intrinsics
from nerfexp.pixels import png_bytes

SIZE = 24


@pytest.fixture(scope="module")
def rendered():
    """The built-in scene seen through a real lens (off-centre, fx != fy, OPENCV), with occluders and masks."""
    lens = real_lens(SIZE, SIZE)
    return {split: occlude(load_procedural(split, n, SIZE, SIZE, supersample=1, lens=lens), seed)
            for seed, (split, n) in enumerate((("train", 6), ("val", 1), ("test", 2)))}


def write(root, rendered) -> None:
    write_nerfstudio(root, rendered.items())


def edit_transforms(root, change) -> None:
    path = root / TRANSFORMS
    content = json.loads(path.read_text())
    change(content)
    path.write_text(json.dumps(content))


def test_a_written_scene_reads_back_to_the_same_rays(tmp_path, rendered):
    write(tmp_path, rendered)
    scene = NerfstudioScene(root=str(tmp_path))
    centre, scale = scene.posed().centre, scene.posed().scale
    for split, views in rendered.items():
        read = scene.views(split)
        assert torch.equal(read.mask, views.mask)
        assert torch.allclose(read.rgba, views.rgba, atol=0.5 / 255)  # 8-bit PNGs
        assert torch.allclose(read.intrinsics.params, views.intrinsics.params, rtol=1e-15)
        assert torch.equal(read.intrinsics.distortion, views.intrinsics.distortion)
        background = torch.ones(3)
        for k in range(len(views)):
            ours, theirs = WholeImages(read, background)[k], WholeImages(views, background)[k]
            assert (ours["directions"] - theirs["directions"]).abs().max() < 1e-6  # float32 rays
            moved = ((theirs["origins"].double() - centre) * scale).float()  # the reader's normalization
            assert (ours["origins"] - moved).abs().max() < 1e-5
            assert torch.equal(ours["mask"], views.mask[k])
    assert scene.split_rule().startswith("the file's train_filenames")


def test_training_rays_never_come_from_masked_pixels(tmp_path, rendered):
    views = rendered["train"]
    stream = iter(RandomRays(views, torch.ones(3), batch_rays=4096, seed=0))
    rgb = next(stream)["rgb"]
    magenta = (rgb - torch.tensor([1.0, 0.0, 1.0])).abs().amax(-1) < 1e-6
    assert not magenta.any()  # every occluder pixel is magenta and masked out; the scene has no magenta
    unmasked = iter(RandomRays(Views(views.rgba, views.c2w, views.intrinsics), torch.ones(3), 4096, 0))
    assert ((next(unmasked)["rgb"] - torch.tensor([1.0, 0.0, 1.0])).abs().amax(-1) < 1e-6).any()


def test_instant_ngp_files_are_read_with_their_defaults(tmp_path):
    # Instant-NGP's colmap2nerf: camera_angle_x instead of fl_x, no cx, cy, w, h or camera_model, images named
    # without an extension, and its box: aabb_scale 2 at scale 0.5 and offset (0.5, 0.5, 0.5) is the cube of
    # half side 2 / (2 x 0.5) = 2 around the origin of the file's coordinates
    views = load_procedural("train", 4, SIZE, SIZE, supersample=1)
    (tmp_path / "images").mkdir()
    frames = []
    for i, image in enumerate(views.rgba):
        (tmp_path / "images" / f"{i}.png").write_bytes(png_bytes((image * 255).round().byte().numpy()))
        frames.append({"file_path": f"./images/{i}", "transform_matrix": views.c2w[i].tolist(), "sharpness": 9})
    (tmp_path / TRANSFORMS).write_text(json.dumps({"camera_angle_x": 0.69, "aabb_scale": 2, "scale": 0.5,
                                                   "offset": [0.5, 0.5, 0.5], "frames": frames}))
    scene = NerfstudioScene(root=str(tmp_path), holdout=2, n_val=1)
    train = scene.views("train")  # frames 1 and 3: every 2nd frame (0, 2) is a test view
    focal = focal_from_fov(SIZE, 0.69)
    assert torch.equal(train.intrinsics.params, torch.tensor([[focal, focal, SIZE / 2, SIZE / 2]] * 2,
                                                             dtype=torch.float64))
    assert not train.intrinsics.is_distorted().any()
    centre, scale = scene.posed().centre, scene.posed().scale
    assert torch.allclose(scene.bounding_box(), ((torch.tensor([[-2.0] * 3, [2.0] * 3], dtype=torch.float64)
                                                  - centre) * scale).float())
    assert scene.split_rule() == "every 2th frame in file_path order a test view (data.holdout)"
    assert len(scene.views("test")) == 2 and len(scene.views("val")) == 1


def test_a_downscaled_folder_is_read_where_it_exists_and_the_images_shrunk_where_not(tmp_path, rendered):
    write(tmp_path, rendered)
    full = NerfstudioScene(root=str(tmp_path)).views("test")
    shrunk = NerfstudioScene(root=str(tmp_path), downscale=2).views("test")  # no images_2/: shrunk on reading
    assert shrunk.rgba.shape[1:3] == (SIZE // 2, SIZE // 2)
    assert torch.allclose(shrunk.intrinsics.params, full.intrinsics.params / 2)
    assert shrunk.mask.sum() < full.mask.sum() / 4 + 1  # a pixel counts where all four under it counted
    (tmp_path / "images_2").mkdir()
    grey = torch.full((SIZE // 2, SIZE // 2, 4), 128, dtype=torch.uint8).numpy()
    for name in ("test_0000.png", "test_0001.png"):
        (tmp_path / "images_2" / name).write_bytes(png_bytes(grey))
    from_folder = NerfstudioScene(root=str(tmp_path), downscale=2).views("test")
    assert torch.all(from_folder.rgba[..., :3] == 128 / 255)  # ns-process-data's images_2, as they are
    assert torch.allclose(from_folder.intrinsics.params, full.intrinsics.params / 2)


MALFORMED = [
    (lambda c: c.pop("fl_x"),
     "frame 0 (images/train_0000.png): missing key 'fl_x' (or Instant-NGP's 'camera_angle_x')"),
    (lambda c: c.update(k1="strong"), "frame 0 (images/train_0000.png): 'k1': expected a finite number"),
    (lambda c: c.update(camera_model="FISHEYE624"), "'camera_model': expected one of PINHOLE, OPENCV"),
    (lambda c: c["frames"][3].update(fl_y=-1.0), "frame 3 (images/train_0003.png): 'fl_y': expected a number of "
                                                  "pixels"),
    (lambda c: c["frames"][1].update(transform_matrix=[[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
     "frame 1: 'transform_matrix' must be a rigid camera pose"),
    (lambda c: c["frames"][0].update(file_path="/etc/passwd"), "frame 0: 'file_path' must be a path inside the "
                                                               "scene's folder"),
    (lambda c: c["frames"][0].update(mask_path="../masks/x.png"), "frame 0: 'mask_path' must be a path inside"),
    (lambda c: c.update(test_filenames=["images/missing.png"]), "'test_filenames' names 'images/missing.png', "
                                                                 "which no frame's 'file_path' is"),
    (lambda c: c.update(applied_transform=[[1, 0, 0]]), "'applied_transform' must be a 3x4 (or 4x4) list"),
    (lambda c: c.update(w=23.5), "'w' must be a whole number of pixels, got 23.5"),
    (lambda c: c.update(aabb_scale=-1), "'aabb_scale' must be a positive number"),
    (lambda c: c.update(k1=-5.0), "folds the image over itself"),
]


@pytest.mark.parametrize(("change", "says"), MALFORMED, ids=[says[:40] for _, says in MALFORMED])
def test_a_malformed_field_is_one_line_naming_the_file_frame_and_key(tmp_path, rendered, change, says):
    write(tmp_path, rendered)
    edit_transforms(tmp_path, change)
    with pytest.raises(DatasetError) as caught:
        scene = NerfstudioScene(root=str(tmp_path))
        for split in ("train", "val", "test"):
            scene.views(split)
    message = str(caught.value)
    assert says in message and str(tmp_path / TRANSFORMS) in message and "\n" not in message


def test_an_image_whose_size_is_not_the_files_and_a_mask_of_another_size_are_refused(tmp_path, rendered):
    write(tmp_path, rendered)
    edit_transforms(tmp_path, lambda c: c.update(w=30))
    says = r"image size 24x24 does not match .*frame 7 \(images/test_0000.png\)'s w x h 30x24"
    with pytest.raises(DatasetError, match=says):
        NerfstudioScene(root=str(tmp_path)).views("test")
    write(tmp_path, rendered)
    small = torch.full((SIZE // 2, SIZE // 2), 255, dtype=torch.uint8).numpy()
    (tmp_path / "masks" / "test_0000.png").write_bytes(png_bytes(small))
    with pytest.raises(DatasetError, match="its mask is 12x12 pixels, its image 24x24"):
        NerfstudioScene(root=str(tmp_path)).views("test")


def test_per_frame_intrinsics_override_the_shared_ones(tmp_path, rendered):
    write(tmp_path, rendered)
    # the file holds 6 train, 1 val and 2 test frames, in that order: frame 8 is the second test view
    edit_transforms(tmp_path, lambda c: c["frames"][8].update(fl_x=40.0, cx=11.0, camera_model="PINHOLE", k1=0,
                                                              k2=0, p1=0, p2=0))
    test = NerfstudioScene(root=str(tmp_path)).views("test")
    lens = real_lens(SIZE, SIZE)
    assert torch.allclose(test.intrinsics.params[0], lens.params)
    assert test.intrinsics.params[1].tolist() == [40.0, lens.params[1].item(), 11.0, lens.params[3].item()]
    assert test.intrinsics.is_distorted().tolist() == [True, False]
    assert math.isclose(test.intrinsics.distortion[0, 0].item(), -0.12)


def test_pinhole_views_stack_with_their_lenses(rendered):
    lenses = Intrinsics.stack([real_lens(SIZE, SIZE), Intrinsics.pinhole(20.0, SIZE, SIZE)])
    assert lenses.params.shape == (2, 4) and lenses.is_distorted().tolist() == [True, False]


# One view, one frame: split lists that share a training frame, frames that name one file under other spellings or
# links, and a copy of a training image at its pose are refused, in one line naming both entries


def frame_like(content: dict, i: int, file_path: str) -> dict:
    """A copy of frame ``i`` of ``content`` naming ``file_path``: the same pose and lens."""
    return {**content["frames"][i], "file_path": file_path}


def remove_images(root) -> None:
    """The scene's images gone: a refusal after this was made before any image was read."""
    for path in (root / "images").iterdir():
        path.unlink()


def test_a_training_frame_in_the_test_list_is_refused_before_any_image_is_read(tmp_path, rendered):
    write(tmp_path, rendered)
    edit_transforms(tmp_path, lambda c: c.update(test_filenames=c["test_filenames"] + ["images/train_0002.png"]))
    remove_images(tmp_path)
    with pytest.raises(DatasetError) as caught:
        NerfstudioScene(root=str(tmp_path)).capture()
    assert str(caught.value) == (f"{tmp_path / TRANSFORMS}: 'test_filenames' and 'train_filenames' both list the "
                                 "frame 'images/train_0002.png': a score on views training saw is no test score; "
                                 "list each frame in one of them")


@pytest.mark.parametrize("listed", ["images//train_0001.png", "images/./train_0001.png", "./images/train_0001.png"])
@pytest.mark.parametrize("split", ["val", "test"])
def test_a_training_frame_listed_in_another_spelling_is_the_same_frame(tmp_path, rendered, listed, split):
    write(tmp_path, rendered)
    edit_transforms(tmp_path, lambda c: c.update({f"{split}_filenames": [listed]}))
    with pytest.raises(DatasetError, match="both list the frame 'images/train_0001.png'"):
        NerfstudioScene(root=str(tmp_path)).capture()


def test_validation_may_list_test_frames(tmp_path, rendered):
    write(tmp_path, rendered)
    edit_transforms(tmp_path, lambda c: c.update(val_filenames=["./images/test_0001.png"]))
    scene = NerfstudioScene(root=str(tmp_path))
    assert torch.equal(scene.views("val").rgba, scene.views("test").rgba[1:])


@pytest.mark.parametrize("spelling", ["images//train_0000.png", "images/./train_0000.png", "images/train_0000"])
def test_two_frames_naming_one_file_are_refused_before_any_image_is_read(tmp_path, rendered, spelling):
    # "images/train_0000" has no extension: read as images/train_0000.png (Blender's way)
    write(tmp_path, rendered)
    edit_transforms(tmp_path, lambda c: c["frames"].append(frame_like(c, 7, spelling)))
    if spelling.endswith(".png"):
        remove_images(tmp_path)  # refused by the names alone
    with pytest.raises(DatasetError) as caught:
        NerfstudioScene(root=str(tmp_path)).capture()
    message = str(caught.value)
    assert "frame 0 (images/train_0000.png)" in message and f"frame 9 ({spelling})" in message, message
    assert "one view counted twice" in message and "\n" not in message


def test_ten_thousand_spellings_of_two_images_are_refused_at_once(tmp_path, rendered):
    # the case, scaled: many frames naming two images in as many spellings are two views, not many
    write(tmp_path, rendered)

    def spelled(k: int) -> str:  # the bits of k as "./" (1) and "/" (0): a spelling of its own for each k
        return "images/" + "".join("./" if bit == "1" else "/" for bit in f"{k:b}") + f"train_000{k % 2}.png"

    def spell(content):
        content["frames"] += [frame_like(content, 7, spelled(k)) for k in range(1, 10_000)]
        content.pop("train_filenames"), content.pop("val_filenames"), content.pop("test_filenames")
    edit_transforms(tmp_path, spell)
    remove_images(tmp_path)
    with pytest.raises(DatasetError, match=r"name one file: one view counted twice"):
        NerfstudioScene(root=str(tmp_path)).capture()


def test_frames_whose_images_are_missing_are_counted_in_one_line_before_any_image_is_read(tmp_path, rendered,
                                                                                          monkeypatch):
    # Instant-NGP's fox lists 67 frames for the 50 images its repository keeps (its loader drops the others); the
    # first missing in file_path order (the frames' order) is named, by its place in the file
    write(tmp_path, rendered)
    for name in ("test_0001.png", "train_0002.png"):
        (tmp_path / "images" / name).unlink()
    monkeypatch.setattr("nerfexp.data.nerfstudio.read_image", lambda *args: pytest.fail("an image was read"))
    with pytest.raises(DatasetError) as caught:
        NerfstudioScene(root=str(tmp_path)).views("train")  # a test view's image missing: refused all the same
    assert str(caught.value) == (
        f"image {tmp_path / 'images' / 'test_0001.png'} does not exist (named by {tmp_path / TRANSFORMS}: frame 8 "
        "(images/test_0001.png)'s file_path), nor do the images of 1 more of the file's 9 frames: nerfexp reads "
        "every frame the file lists (Instant-NGP's loader skips such frames); remove them from the file, bring their "
        "images, or leave them out with data.missing_images=skip")


@pytest.mark.parametrize("lists", [True, False], ids=["split lists", "holdout"])
def test_frames_whose_images_are_missing_are_left_out_with_skip_and_named_once(tmp_path, rendered, caplog, lists):
    # as Instant-NGP's loader does (its fox: 67 frames, 50 images): the other frames are the scene, whole
    write(tmp_path, rendered)
    if not lists:
        edit_transforms(tmp_path, lambda content: [content.pop(k) for k in ("train_filenames", "val_filenames",
                                                                            "test_filenames")])
    for name in ("train_0001.png", "test_0000.png"):
        (tmp_path / "images" / name).unlink()
    scene = NerfstudioScene(root=str(tmp_path), missing_images="skip")
    with caplog.at_level("WARNING", "nerfexp"):
        read = [scene.views(split) for split in ("train", "val", "test")]
    left_out = ["images/test_0000.png", "images/train_0001.png"]  # in the file's order (file_path order)
    assert scene.frames_left_out() == left_out
    files = [source.path.name for views in read for source in views.sources]
    assert not {"train_0001.png", "test_0000.png"} & set(files)
    assert len(scene.posed().capture.frames) == len(set(files)) == 7  # every frame left read, in some split
    assert caplog.text.count("frames do not exist") == 1 and (
        f"{tmp_path / TRANSFORMS}: the images of 2 of its 9 frames do not exist (the first: images/test_0000.png): "
        "those frames are left out (data.missing_images=skip; results.json's frames_left_out lists them)"
        in caplog.text)
    assert NerfstudioScene(root=str(tmp_path)).frames_left_out() is None  # refuse, the default, leaves none out


def test_a_file_none_of_whose_images_exist_is_refused_with_skip(tmp_path, rendered):
    write(tmp_path, rendered)
    shutil.rmtree(tmp_path / "images")
    with pytest.raises(DatasetError, match=r"transforms.json: none of the images of its 9 frames exists \(the "
                                           r"first: .*images/test_0000.png\)$"):
        NerfstudioScene(root=str(tmp_path), missing_images="skip").capture()


@pytest.mark.parametrize("link", [os.symlink, os.link], ids=["symbolic", "hard"])
def test_a_link_to_a_training_image_is_refused_before_any_image_is_read(tmp_path, rendered, link):
    write(tmp_path, rendered)
    link("train_0003.png" if link is os.symlink else tmp_path / "images" / "train_0003.png",
         tmp_path / "images" / "linked.png")

    def add(content):
        content["frames"].append(frame_like(content, 0, "images/linked.png"))
        content["test_filenames"].append("images/linked.png")
    edit_transforms(tmp_path, add)
    with pytest.raises(DatasetError) as caught:
        NerfstudioScene(root=str(tmp_path)).capture()
    assert str(caught.value) == (f"{tmp_path / TRANSFORMS}: frame 9 (images/linked.png) and {tmp_path / TRANSFORMS}: "
                                 f"frame 3 (images/train_0003.png) name one file ({tmp_path / 'images/linked.png'}): "
                                 "one view counted twice; list each image once")


def test_a_copy_of_a_training_image_at_its_pose_is_refused_before_training(tmp_path, rendered):
    write(tmp_path, rendered)
    shutil.copy(tmp_path / "images" / "train_0004.png", tmp_path / "images" / "copy.png")
    shutil.copy(tmp_path / "masks" / "train_0004.png", tmp_path / "masks" / "copy.png")

    def add(content):
        train = content["frames"][4]
        assert train["file_path"] == "images/train_0004.png"
        content["frames"].append({**train, "file_path": "images/copy.png", "mask_path": "masks/copy.png"})
        content["test_filenames"].append("images/copy.png")
    edit_transforms(tmp_path, add)
    data = RayDataModule(NerfstudioScene(root=str(tmp_path)), batch_rays=64)
    with pytest.raises(DatasetError) as caught:
        data.setup("fit")
    assert str(caught.value) == (
        f"the test view {tmp_path / TRANSFORMS}: frame 9 (images/copy.png) and the training view "
        f"{tmp_path / TRANSFORMS}: frame 4 (images/train_0004.png) are one view (they have the same pixels and the "
        "same pose): a score on views training saw is no test score; keep it in one split")


def test_honest_splits_load_and_every_view_names_its_frame(tmp_path, rendered):
    write(tmp_path, rendered)
    data = RayDataModule(NerfstudioScene(root=str(tmp_path)), batch_rays=64)
    data.setup("fit")
    scored = data.scored_views("fit")
    assert set(scored) == {"val", "test"} and len(scored["test"]) == 2
    assert [source.name for source in scored["test"].sources] == [
        f"{tmp_path / TRANSFORMS}: frame {i} (images/test_000{k}.png)" for i, k in ((7, 0), (8, 1))]


@settings(max_examples=100, deadline=None)
@given(st.sampled_from(["./", ""]), st.lists(st.sampled_from(["./", "/", ""]), min_size=2, max_size=2))
def test_every_spelling_of_a_frames_file_is_matched_to_it(tmp_path_factory, lead, extra):
    # independent truth: the file system, which reads each spelling as the same file (a leading "/" is absolute:
    # refused by relative_file)
    root = tmp_path_factory.mktemp("spellings")
    (root / "images" / "a").mkdir(parents=True)
    (root / "images" / "a" / "x.png").write_bytes(b"")
    spelled = f"{lead}images/{extra[0]}a/{extra[1]}x.png"
    assert os.path.samefile(scene_file(root, spelled), root / "images/a/x.png")
    assert spelling(spelled) == "images/a/x.png"
