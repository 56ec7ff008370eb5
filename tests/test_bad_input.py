"""Bad settings and bad data through the command line: exit status 1, one line on stderr naming the key
the user set (or the file) and what was expected, no traceback, and nothing written that should not be."""

import json
import re
import shutil
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st
from PIL import Image

from nerfexp.domains import FLOAT32_TOP_OCTAVE
from nerfexp.errors import ConfigError
from nerfexp.settings.groups import check_group_overrides, is_nerfexp_group
from tests.helpers import one_error_line, run_nerfexp


@pytest.mark.parametrize(("overrides", "message"), [
    (["scale.lr=-1"], "scale.lr=-1 (which sets model.optimizer.lr): expected a finite number > 0 and <= 1"),
    (["scale.batch_rays=0"], "scale.batch_rays=0 (which sets datamodule.batch_rays): expected a whole number in "
                             "[1, 2^63 - 1]"),
    (["trainer.max_steps=0"], "trainer.max_steps=0: expected a whole number in [1, 2^63 - 1]"),
    (["scale.val_every=0"], "scale.val_every=0 (which sets trainer.val_check_interval): expected a whole number in "
                            "[1, 2^63 - 1]"),
    (["scale.n_coarse=0"], "scale.n_coarse=0 (which sets sampler.n_coarse): expected a whole number in [1, 2^63 - 1]"),
    (["encoding.position.n_freqs=-1"], "encoding.position.n_freqs=-1: expected a whole number in [0, 2^63 - 1]"),
    (["encoding.position.n_freqs=60"], "encoding.position.n_freqs=60, scale.position_input_scale=1.0 (which sets "
                                       "encoding.position.input_scale): expected at most 19 frequencies with "
                                       f"input_scale 1: frequencies above 2^{FLOAT32_TOP_OCTAVE} pi are noise for "
                                       "float32 positions (docs/numerics.md)"),
    (["scale.position_input_scale=0"], "scale.position_input_scale=0 (which sets encoding.position.input_scale): "
                                       "expected a finite number > 0 and <= 262144"),
    (["data.n_train=0"], "data.n_train=0: expected a whole number in [1, 2^63 - 1], or null (all)"),
    (["data.n_val=0"], "data.n_val=0: expected a whole number in [1, 2^63 - 1]"),
    # issue 27 section 5: every key a user sets has a domain (nerfexp.settings.schema.SCHEMA); Hydra's own errors
    (["seed=abc"], "seed=abc: expected a whole number in [0, 4294967295]"),
    (["view_dependence=sh", "view_dependence.degree=7"], "view_dependence.degree=7: expected a whole number in [0, 3]"),
    (["scale.image_size=-32"], "scale.image_size=-32 (which sets data.image_size): expected a whole number in [1, "
                               "2^63 - 1]"),
    # issue 39 section 4: extreme values, one line each (traceback and overflow before)
    (["data.far=1e308"], "data.far=1e+308 (which sets model.renderer.far): expected a finite number > 0 and <= 2^24, "
                         "or null (from the scene)"),
    # a thread count beyond any machine: refused before torch is asked for it (OpenMP aborted the process, with no
    # line, and left the run's status.json saying running; torch overflowed past 2^31 - 1)
    (["threads=1000000000"], "threads=1000000000: expected a whole number in [1, 65536], or null (auto: the CPUs "
                             "this process may use over the jobs run at once)"),
    (["threads=9223372036854775807"], "threads=9223372036854775807: expected a whole number in [1, 65536], or null "
                                      "(auto: the CPUs this process may use over the jobs run at once)"),
    # a setting with a physical meaning has a range that means something: pose noise in degrees up to the largest
    # turn and a fraction of the cameras' radius up to 1 ([1e9,1e9] moved every camera 4e9 units away, scored as any
    # other run)
    (["datamodule.pose_noise=[1e9,1e9]"], "datamodule.pose_noise=[1000000000.0, 1000000000.0]: expected [degrees, "
                                          "fraction of the cameras' radius], degrees a finite number in [0, 180] and "
                                          "fraction one in [0, 1], or null (the poses as the data gives them)"),
    (["hierarchical=false", "scale.n_fine=64"], "scale.n_fine=64: not used with hierarchical=false (one network of "
                                                "sampler.n_single samples; set scale.n_single)"),
    (["acceleration=occupancy", "acceleration.grid.segments=8"],
     "acceleration.grid.segments=8: not used with acceleration.grid.early_stop_transmittance=0 (no early "
     "termination: set it > 0, e.g. 1e-4, to march in segments)"),
    (["encoding=bogus"], "encoding=bogus: no such option (choose from hashgrid, none, posenc)"),
    (["scale.lrr=1"], "scale.lrr=1: no such key (scale has steps, lr, lr_final, lr_warmup_steps, batch_rays, depth, "
                      "width, skips, view_hidden, n_coarse, n_fine, n_single, chunk, val_every, image_size, "
                      "position_input_scale, max_side, test_stride; the closest: scale.lr)"),
    (["encoding=hashgrid", "scale.hash_finest=64"], "scale.hash_finest=64: no such key (scale has steps, lr, "
                                                    "lr_final, lr_warmup_steps, batch_rays, depth, width, skips, "
                                                    "view_hidden, n_coarse, n_fine, n_single, chunk, val_every, "
                                                    "image_size, position_input_scale, max_side, test_stride; it "
                                                    "moved to encoding.position.finest)"),
    (["encoding=hashgrid", "encoding.position.sparse_gradients=true"],
     "encoding.position.sparse_gradients=true and model.optimizer._target_=torch.optim.Adam: expected an optimizer "
     "that takes sparse gradients (nerfexp.training.optimizers.LazyAdam), or set "
     "encoding.position.sparse_gradients=false"),
    (["trainer.max_step=3"], "trainer.max_step=3: no such key (trainer has _target_, accelerator, devices, precision, "
                             "max_steps, val_check_interval, check_val_every_n_epoch, num_sanity_val_steps, "
                             "log_every_n_steps, default_root_dir, enable_progress_bar, enable_model_summary, "
                             "plugins; the closest: trainer.max_steps; +trainer.max_step=3 adds one)"),
])
def test_a_bad_setting_is_one_line_before_the_run_directory_is_made(tmp_path, overrides, message):
    result = run_nerfexp(*overrides, f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert one_error_line(result) == f"nerfexp: error: {message}"
    assert not (tmp_path / "run").exists()


def test_a_keyword_its_class_refuses_is_one_line(tmp_path, tiny):
    # +trainer.KEY is handed to lightning.Trainer, which checks it when the run builds it
    result = run_nerfexp(*tiny, "+trainer.gradient_clip_val=abc", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    line = one_error_line(result)
    assert line.startswith("nerfexp: error: Error in call to target 'lightning.pytorch.trainer.trainer.Trainer'")
    assert "`gradient_clip_val` should be an int or a float. Got abc." in line
    assert len(result.stderr.splitlines()) == 1, result.stderr
    assert not (tmp_path / "run" / "metrics.jsonl").exists()


def test_eight_times_lower_positions_allow_three_more_octaves(tmp_path):
    # gamma(x / 8): L = 22 puts its top frequency 2^21 pi x / 8 = 2^18 pi x at the limit; L = 23 is past it
    result = run_nerfexp("encoding.position.n_freqs=23", "scale.position_input_scale=0.125",
                         f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert "expected at most 22 frequencies with input_scale 0.125" in one_error_line(result)


def blender_scene(tmp_path, tiny, form: str = "blender") -> tuple:
    """A scene of 10 training, 1 validation and 2 test views written by nerfexp-scene in ``form`` (Blender's or
    nerfstudio's format), and the tiny run's overrides for it."""
    scene = tmp_path / "scene"
    exported = run_nerfexp(str(scene), "--resolution", "24", "--n-train", "10", "--n-val", "1", "--n-test", "2",
                           "--format", form, cwd=tmp_path, script="nerfexp-scene")
    assert exported.returncode == 0, exported.stderr[-2000:]
    overrides = [o for o in tiny if not o.startswith(("data.", "scale.image_size"))]
    return scene, [f"data={form}", f"data.root={scene}", "data.n_val=1", *overrides]


def test_more_training_views_than_a_scene_has_is_one_line(tmp_path, tiny):
    scene, overrides = blender_scene(tmp_path, tiny)
    result = run_nerfexp(*overrides, "data.n_train=11", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    line = one_error_line(result)
    assert line == f"nerfexp: error: data.n_train=11: {scene / 'transforms_train.json'} has only 10 views"
    assert not (tmp_path / "run" / "metrics.jsonl").exists()


def test_a_bad_pose_in_the_test_split_stops_the_run_before_its_first_step(tmp_path, tiny):
    scene, overrides = blender_scene(tmp_path, tiny)
    transforms = scene / "transforms_test.json"
    content = json.loads(transforms.read_text())
    content["frames"][1]["transform_matrix"][0][3] = float("nan")
    transforms.write_text(json.dumps(content))  # Python writes NaN, which JSON readers accept
    result = run_nerfexp(*overrides, f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    line = one_error_line(result)
    assert line.startswith(f"nerfexp: error: {transforms}: frame 1: 'transform_matrix' must be a rigid camera pose")
    assert not (tmp_path / "run" / "metrics.jsonl").exists() and not (tmp_path / "run" / "checkpoints").exists()


def test_a_test_split_naming_a_training_image_stops_the_run_before_its_first_step(tmp_path, tiny):
    # the same image under another spelling: its "test" score would be a score on a view training saw
    scene, overrides = blender_scene(tmp_path, tiny)
    transforms = scene / "transforms_test.json"
    content = json.loads(transforms.read_text())
    content["frames"][0]["file_path"] = "train//r_4.png"  # frame 0: scored at every scale.test_stride
    transforms.write_text(json.dumps(content))
    result = run_nerfexp(*overrides, f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert one_error_line(result) == (
        f"nerfexp: error: the test view {transforms}: frame 0 (train//r_4.png) and the training view "
        f"{scene / 'transforms_train.json'}: frame 4 (./train/r_4) are one view (they name one file "
        f"({scene / 'train' / 'r_4.png'})): a score on views training saw is no test score; keep it in one split")
    assert not (tmp_path / "run" / "metrics.jsonl").exists() and not (tmp_path / "run" / "checkpoints").exists()


def add_test_frame(scene, form: str, frame: dict) -> tuple[Path, int]:
    """``frame`` added to the test split of an exported scene (``blender_scene``) where it is scored (Blender's:
    first, a test view at every ``scale.test_stride``; nerfstudio's: last, listed in ``test_filenames``); its
    transforms file and its place there."""
    transforms = scene / ("transforms_test.json" if form == "blender" else "transforms.json")
    content = json.loads(transforms.read_text())
    place = 0 if form == "blender" else len(content["frames"])
    content["frames"].insert(place, frame)
    if form == "nerfstudio":
        content["test_filenames"].append(frame["file_path"])
    transforms.write_text(json.dumps(content))
    return transforms, place


@pytest.mark.parametrize("form", ["blender", "nerfstudio"])
def test_a_near_copy_of_a_training_view_in_the_test_split_stops_the_run_before_its_first_step(tmp_path, tiny, form):
    # a training image copied to another file, at that view's pose plus 1e-6 on one translation entry
    scene, overrides = blender_scene(tmp_path, tiny, form)
    train = scene / ("transforms_train.json" if form == "blender" else "transforms.json")
    frame = json.loads(train.read_text())["frames"][4]
    image = scene / (f"{frame['file_path']}.png" if form == "blender" else frame["file_path"])
    shutil.copy(image, image.with_name("copy.png"))
    frame["transform_matrix"][0][3] += 1e-6
    name = ("./train/copy" if form == "blender" else "images/copy.png")
    transforms, place = add_test_frame(scene, form, {**frame, "file_path": name})
    result = run_nerfexp(*overrides, f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    expected = re.escape(f"nerfexp: error: the test view {transforms}: frame {place} ({name}) and the training view "
                         f"{train}: frame 4 ({frame['file_path']}) are one view (their cameras ") + r"[0-9.e-]+" + \
        re.escape(" of the cameras' spread and 0 degrees apart, their images identical: one view is cameras within "
                  "0.01 of the spread and 0.5 degrees, images at 20 dB or more): a score on views training saw is no "
                  "test score; keep it in one split")
    assert re.fullmatch(expected, one_error_line(result))
    assert not (tmp_path / "run" / "metrics.jsonl").exists() and not (tmp_path / "run" / "checkpoints").exists()


@pytest.mark.parametrize("form", ["blender", "nerfstudio"])
def test_a_file_path_holding_a_nul_byte_is_one_line_before_any_image_is_read(tmp_path, tiny, form):
    scene, overrides = blender_scene(tmp_path, tiny, form)
    frame = json.loads((scene / ("transforms_train.json" if form == "blender" else "transforms.json")).read_text())
    name = "images/a\x00.png"
    transforms, place = add_test_frame(scene, form, {**frame["frames"][0], "file_path": name})
    result = run_nerfexp(*overrides, f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert one_error_line(result) == (f"nerfexp: error: {transforms}: frame {place}: 'file_path' holds a NUL "
                                      "byte, which no file name can, got 'images/a\\x00.png'")
    assert not (tmp_path / "run" / "metrics.jsonl").exists()


@pytest.mark.parametrize("mode", ["run", "sweep"])
def test_a_run_or_sweep_directory_that_cannot_be_written_is_one_line(tmp_path, tiny, mode):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory")
    if mode == "run":
        result = run_nerfexp(*tiny, f"hydra.run.dir={blocker / 'run'}", cwd=tmp_path)
    else:
        result = run_nerfexp("-m", *tiny, "seed=0,1", f"hydra.sweep.dir={blocker / 'sweep'}", cwd=tmp_path)
    assert one_error_line(result) == (f"nerfexp: error: cannot write the {mode} directory {blocker / mode}: "
                                      f"Not a directory (choose another with hydra.{mode}.dir=...)")


def flip_a_byte_of_image_data(scene) -> tuple:
    path = scene / "train" / "r_3.png"
    data = bytearray(path.read_bytes())
    data[data.index(b"IDAT") + 12] ^= 0x20
    path.write_bytes(bytes(data))
    return path, "a damaged or unreadable image file (broken PNG file (bad header checksum in b'IDAT'))"


def oversized_image(scene) -> tuple:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    path = scene / "test" / "r_0.png"
    header = struct.pack(">IIBBBBB", 20_000, 20_000, 8, 6, 0, 0, 0)  # 400 million RGBA pixels
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\0"))
                     + chunk(b"IEND", b""))
    return path, "pixels, which nerfexp does not decode"


def zero_pose(scene) -> tuple:
    path = scene / "transforms_val.json"
    content = json.loads(path.read_text())
    content["frames"][0]["transform_matrix"] = [[0] * 4] * 4
    path.write_text(json.dumps(content))
    return path, "frame 0: 'transform_matrix' must be a rigid camera pose, but its last row is [0.0, 0.0, 0.0, 0.0]"


def rgb_among_rgba(scene) -> tuple:
    path = scene / "train" / "r_4.png"
    Image.open(path).convert("RGB").save(path)  # re-saved without its alpha channel, as an editor may
    return path, f"an RGB image (no alpha), but {scene / 'train' / 'r_0.png'} is an RGBA image: "


@pytest.mark.slow
@pytest.mark.parametrize("damage", [flip_a_byte_of_image_data, oversized_image, zero_pose, rgb_among_rgba])
def test_bad_data_in_any_split_stops_the_run_before_its_first_step(tmp_path, tiny, damage):
    scene, overrides = blender_scene(tmp_path, tiny)
    path, message = damage(scene)
    result = run_nerfexp(*overrides, f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    line = one_error_line(result)
    assert line.startswith(f"nerfexp: error: {path}") and message in line, line
    assert not (tmp_path / "run" / "metrics.jsonl").exists() and not (tmp_path / "run" / "checkpoints").exists()


def big_cameras(tmp_path) -> str:
    """A --cameras file of one camera whose frames are 200,000 pixels square."""
    path = tmp_path / "cameras.json"
    identity = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 4.0], [0.0, 0.0, 0.0, 1.0]]
    lens = {"camera_model": "PINHOLE", "fl_x": 100.0, "fl_y": 100.0, "cx": 100_000.0, "cy": 100_000.0}
    path.write_text(json.dumps({"height": 200_000, "width": 200_000, **lens, "c2w": [identity]}))
    return str(path)


@pytest.mark.parametrize(("prog", "args", "message"), [
    ("nerfexp-export", ["--resolution", "100000"], "argument --resolution: 100000: a grid of 100000^3 densities "
                                                   "needs about"),
    ("nerfexp-export", ["--threshold", "nan"], "argument --threshold: expected a finite number > 0 and <= "
                                               "3.40282e+38, got nan"),  # float32's largest: densities are float32
    ("nerfexp-export", ["--threshold", "inf"], "argument --threshold: expected a finite number > 0 and <= "
                                               "3.40282e+38, got inf"),
    ("nerfexp-export", ["--threshold", "1e39"], "argument --threshold: expected a finite number > 0 and <= "
                                                "3.40282e+38, got 1e39"),
    ("nerfexp-view", ["--max-width", "9" * 400], f"argument --max-width: {'9' * 400}: a frame of "),
    ("nerfexp-view", ["--port", "70000"], "argument --port: expected a port in 1..65535 (0: any free one), got 70000"),
    ("nerfexp-render", ["--size", "200000"], "argument --size: 200000: a frame of 200000 x 200000 pixels needs about"),
    ("nerfexp-render", ["--cameras", big_cameras], "a frame of 200000 x 200000 pixels needs about"),
])
def test_an_argument_out_of_its_domain_or_too_big_for_memory_is_one_line_before_the_run_is_read(
        tmp_path, capsys, prog, args, message):
    # the run does not exist: each argument is refused before the run is looked for
    from nerfexp.commands import export, render, view
    main = {"nerfexp-export": export.main, "nerfexp-render": render.main, "nerfexp-view": view.main}[prog]
    args = [arg(tmp_path) if callable(arg) else arg for arg in args]
    with pytest.raises(SystemExit) as ended:
        main([str(tmp_path / "no_run"), *args])
    assert ended.value.code != 0
    stderr = capsys.readouterr().err + (ended.value.code if isinstance(ended.value.code, str) else "")
    (line,) = [line for line in stderr.splitlines() if line.startswith(f"{prog}: error:")]
    assert message in line and "Traceback" not in stderr
    if "needs about" in message:
        assert "of memory, more than this machine's" in line
    assert not (tmp_path / "no_run").exists()


@pytest.mark.parametrize("args", [["--resolution", "100000"], ["--n-train", "10000000"]])
def test_a_scene_too_big_for_memory_is_one_line_before_anything_is_written(tmp_path, capsys, args):
    from nerfexp.commands import scene
    with pytest.raises(SystemExit) as ended:
        scene.main([str(tmp_path / "scene"), *args])
    assert ended.value.code == "nerfexp-scene: error: " + ended.value.code.split(": error: ", 1)[1]
    assert "a split of" in ended.value.code and "of memory, more than this machine's" in ended.value.code
    assert not (tmp_path / "scene").exists() and list(tmp_path.iterdir()) == []


@pytest.mark.slow
@pytest.mark.parametrize("prog", ["nerfexp-render", "nerfexp-export", "nerfexp-view"])
def test_a_chunk_too_big_for_memory_is_one_line_before_any_rendering(tiny_run, tmp_path, prog):
    from nerfexp.commands import export, render, view
    main = {"nerfexp-export": export.main, "nerfexp-render": render.main, "nerfexp-view": view.main}[prog]
    before = sorted(p.relative_to(tiny_run) for p in tiny_run.rglob("*"))
    with pytest.raises(SystemExit) as ended:
        main([str(tiny_run), "--chunk", "99999999999"])
    assert ended.value.code.startswith(f"{prog}: error: --chunk 99999999999: an evaluation of 99999999999 rays x 48 "
                                       "samples needs about")
    assert sorted(p.relative_to(tiny_run) for p in tiny_run.rglob("*")) == before


@pytest.mark.parametrize(("entry", "args", "code", "said"), [
    ("nerfexp.commands.train:cli", ["scale.image_size=-32"], 1, "nerfexp: error: scale.image_size=-32"),
    ("nerfexp.commands.train:cli", ["trainer.precision=bogus"], 1, "nerfexp: error: trainer.precision=bogus"),
    ("nerfexp.commands.train:cli", ["--help"], 0, "nerfexp"),
    ("nerfexp.commands.render:main", ["no_run"], 1, "nerfexp-render: error: no_run does not exist"),
    ("nerfexp.commands.evaluate:main", ["no_run"], 1, "nerfexp-eval: error: no_run does not exist"),
])
def test_a_command_that_stops_at_bad_input_or_help_does_not_import_lightning(entry, args, code, said, tmp_path):
    # importing Lightning is most of a command's start-up (docs/testing.md): bad input is said without it;
    # trainer.precision=bogus reads Lightning's own list of precisions to name them, and so imports it
    module, function = entry.split(":")
    program = ("import atexit, sys; atexit.register(lambda: print('lightning imported:', 'lightning' in sys.modules)); "
               f"sys.argv = ['command', *{args!r}]; from {module} import {function}; {function}()")
    result = subprocess.run([sys.executable, "-c", program], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == code, result.stderr[-2000:]
    assert said in result.stdout + result.stderr
    lightning = "precision" in args[0]
    assert result.stdout.rstrip().endswith(f"lightning imported: {lightning}"), result.stdout[-2000:]
    assert list(tmp_path.iterdir()) == []  # nothing made


# A config group's choice is an option's name: null, a number, a mapping or a range there is one line (a
# ValueError's traceback from Hydra before), and GROUP=null is refused rather than read as no option; a list or a
# path, which Hydra composes and records as another choice (none, or the path), too (every group:
# tests/settings/test_groups.py).
LIST = "; a list is not one (Hydra would compose each config it names and record no choice)"
SWEEPS = ", ".join(sorted(path.stem for path in (Path(__file__).parents[1] / "conf" / "sweeps").glob("*.yaml")))
PATH = "; a path is not one (Hydra would compose whatever config it leads to, in another group too)"

@pytest.mark.parametrize(("arguments", "message"), [
    (["experiment=null"], "experiment=null: a config group takes an option's name (choose from fast); none is "
                          "experiment's default: leave it out for none"),
    (["+ablation=null"], "+ablation=null: a config group takes an option's name (choose from complete, "
                         "far_fewer_images, fewer_frequencies, fewer_images, more_frequencies, no_hierarchical, "
                         "no_pe_vd_h, no_posenc, no_view_dependence); none is ablation's default: leave it out for none"),
    (["encoding=null"], "encoding=null: a config group takes an option's name (choose from hashgrid, none, posenc)"),
    (["logger=true"], "logger=true: a config group takes an option's name (choose from csv, mlflow, none, "
                      "tensorboard, wandb)"),
    (["-m", "experiment=fast,null"], "experiment=fast,null: a config group takes an option's name (choose from "
                                     "fast); none is experiment's default: leave it out for none"),
    (["-m", "scale=range(0,2)"], "scale=range(0,2): a config group takes an option's name (choose from cpu, paper)"),
    (["experiment=[fast]"], f"experiment=[fast]: a config group takes an option's name (choose from fast){LIST}"),
    (["experiment=../ablation/no_posenc"], "experiment=../ablation/no_posenc: a config group takes an option's name "
                                           f"(choose from fast){PATH}"),
    (["experiment=/ablation/no_posenc"], "experiment=/ablation/no_posenc: a config group takes an option's name "
                                         f"(choose from fast){PATH}"),
    (["experiment=fast/../fast"], f"experiment=fast/../fast: a config group takes an option's name (choose from fast)"
                                  f"{PATH}"),
    (["scale=./paper"], f"scale=./paper: a config group takes an option's name (choose from cpu, paper){PATH}"),
    (["-m", "seed=0,1", "experiment=fast,../ablation/no_posenc"],
     f"experiment=fast,../ablation/no_posenc: a config group takes an option's name (choose from fast){PATH}"),
    (["-m", "encoding=[none],[posenc]"], "encoding=[none],[posenc]: a config group takes an option's name (choose "
                                         f"from hashgrid, none, posenc){LIST}"),
    (["+sweeps=[smoke]"], f"+sweeps=[smoke]: a config group takes an option's name (choose from {SWEEPS}){LIST}"),
])
def test_a_group_given_what_is_not_an_option_is_one_line_before_anything_is_made(tmp_path, arguments, message):
    result = run_nerfexp(*arguments, f"hydra.run.dir={tmp_path / 'run'}", f"hydra.sweep.dir={tmp_path / 'sweep'}",
                         cwd=tmp_path)
    assert one_error_line(result) == f"nerfexp: error: {message}"
    assert list(tmp_path.iterdir()) == []


def test_removing_a_group_or_choosing_its_options_is_not_refused():
    check_group_overrides(["~experiment", "~experiment=fast", "experiment=fast", "-m", "encoding=posenc,none",
                           "encoding=glob(*)", "scale.lr=0.1", "data.root=/x=y", "hydra.run.dir=/a/b", "--cfg", "job",
                           "hydra/launcher=submitit_local", "+encoding/hashgrid_sizes=paper", "tags=[a/b]"],
                          is_nerfexp_group)


@given(st.sampled_from(["experiment", "+experiment", "++encoding", "view_dependence", "hydra/launcher"]),
       st.one_of(st.none(), st.booleans(), st.integers(), st.floats(allow_nan=False, allow_infinity=False),
                 st.dictionaries(st.sampled_from("ab"), st.integers(), min_size=1, max_size=2)))
def test_any_value_but_an_options_name_at_a_group_is_refused(key, value):
    text = {None: "null", True: "true", False: "false"}.get(value, value) if not isinstance(value, dict) else (
        "{" + ",".join(f"{k}:{v}" for k, v in value.items()) + "}")
    argument = f"{key}={text}"
    with pytest.raises(ConfigError) as raised:
        check_group_overrides([argument, "encoding=posenc"], is_nerfexp_group)
    assert str(raised.value).startswith(f"{argument}: a config group takes an option's name")
