"""One folder of an archive unpacked (nerfexp.data.archives): exactly the files under it, byte for byte, and every
member that would leave it, every link or device, and every member or total over its bound refused before anything
is written, zip and tar alike."""

import re

import pytest

from nerfexp.data.archives import MEMBER_BYTES, Limits, unpack_folder
from nerfexp.errors import DatasetError
from tests.data.archive_files import KINDS, Item, archive_bytes, declaring, folder_files, scene_items, zip_bytes


@pytest.fixture(params=KINDS)
def kind(request) -> str:
    return request.param


def written(tmp_path, kind: str, items: list[Item]):
    """The archive of ``items`` written to a file, and an empty folder to unpack into."""
    archive = tmp_path / f"scene.{kind}"
    archive.write_bytes(archive_bytes(kind, items))
    destination = tmp_path / "out"
    destination.mkdir()
    return archive, destination


def test_the_folder_asked_for_is_unpacked_exactly_and_nothing_beside_it(tmp_path, kind):
    items = scene_items("nerf_synthetic/lego") + scene_items("nerf_synthetic/ship", seed=5)[1:]  # one README
    archive, destination = written(tmp_path, kind, items)
    total = unpack_folder(archive, "nerf_synthetic/lego", destination)
    expected = {item.name.removeprefix("nerf_synthetic/lego/"): item.data for item in items
                if item.name.startswith("nerf_synthetic/lego/") and item.kind == "file"}
    assert folder_files(destination) == expected and len(expected) == 13  # 10 images, 3 transforms files
    assert total == sum(map(len, expected.values()))


def test_a_folder_given_with_a_trailing_slash_or_dot_parts_is_the_same_folder(tmp_path, kind):
    items = scene_items("data/nerf/fox")
    archive, destination = written(tmp_path, kind, items)
    unpack_folder(archive, "./data/nerf/fox/", destination)
    assert set(folder_files(destination)) == {i.name.removeprefix("data/nerf/fox/") for i in items
                                              if i.kind == "file" and i.name != "README"}


ESCAPING = {  # name -> what it would write outside the folder
    "lego/../../outside.png": "climbs out of the folder",
    "../lego/r_0.png": "climbs out of the folder it is unpacked into",
    "/etc/lego.png": "an absolute name",
    "C:/lego/r_0.png": "a Windows drive",
    "lego\\..\\..\\outside.png": "climbs with Windows separators",
}


@pytest.mark.parametrize("name", ESCAPING, ids=ESCAPING.values())
def test_a_member_whose_name_leaves_the_folder_is_refused_before_anything_is_written(tmp_path, kind, name):
    archive, destination = written(tmp_path, kind, [*scene_items("lego"), Item(name, data=b"x")])
    with pytest.raises(DatasetError) as refused:
        unpack_folder(archive, "lego", destination)
    assert str(refused.value) == (f"{archive}: member {name!r} would be written outside the folder it is unpacked "
                                  "into (an absolute name or '..'): the archive is refused")
    assert list(destination.iterdir()) == []


@pytest.mark.parametrize("kind, link", [("zip", "symlink"), ("zip", "device"), ("tar.gz", "symlink"),
                                        ("tar.gz", "hardlink"), ("tar.gz", "device")])  # zip has no hard links
@pytest.mark.parametrize("where", ["lego/train/r_9.png", "elsewhere/r_9.png"], ids=["in the folder", "beside it"])
def test_a_link_or_a_device_anywhere_in_the_archive_is_refused(tmp_path, kind, link, where):
    archive, destination = written(tmp_path, kind, [*scene_items("lego"), Item(where, link, b"/etc/passwd")])
    with pytest.raises(DatasetError) as refused:
        unpack_folder(archive, "lego", destination)
    what = "a link" if link != "device" else "a device file"
    assert str(refused.value) == (f"{archive}: member {where!r} is {what}, not a file or a folder: the archive is "
                                  "refused (a scene is files in folders)")
    assert list(destination.iterdir()) == []


def test_a_zip_whose_index_declares_a_member_over_the_bound_is_refused_before_it_is_read(tmp_path):
    # a "zip bomb": a few bytes that its index says unpack to 3.75 GiB, above the 2 GiB of one file
    bomb = declaring(zip_bytes([Item("lego/transforms_train.json", data=b"{}")]), 0xF000_0000)
    archive = tmp_path / "bomb.zip"
    archive.write_bytes(bomb)
    (destination := tmp_path / "out").mkdir()
    with pytest.raises(DatasetError) as refused:
        unpack_folder(archive, "lego", destination)
    assert str(refused.value) == (f"{archive}: member 'lego/transforms_train.json' declares {0xF000_0000:,} bytes, "
                                  f"more than the {MEMBER_BYTES:,} nerfexp unpacks of one file: the archive is refused")
    assert list(destination.iterdir()) == []


@pytest.mark.parametrize("limits, refusal", [
    (Limits(member_bytes=100), "declares"),  # one image of the scene is over 100 bytes
    (Limits(total_bytes=1000), "holds more than 1,000 bytes"),
    (Limits(members=5), "or 5 members"),
], ids=["one member", "the total", "the count"])
def test_a_folder_over_its_bounds_is_refused_before_anything_is_written(tmp_path, kind, limits, refusal):
    archive, destination = written(tmp_path, kind, scene_items("lego"))
    with pytest.raises(DatasetError, match=refusal):
        unpack_folder(archive, "lego", destination, limits)
    assert list(destination.iterdir()) == []


@pytest.mark.filterwarnings("ignore:Duplicate name")  # the zip made with a name twice
@pytest.mark.parametrize("items, refusal", [
    ([Item("lego/a.png", data=b"1"), Item("lego/a.png", data=b"2")], "'lego/a.png' names a file twice"),
    ([Item("lego/a", data=b"1"), Item("lego/a/b.png", data=b"2")], "'a' under 'lego' is a file and a folder"),
    ([Item("lego/a/b.png", data=b"1"), Item("lego/a", data=b"2")], "'lego/a' names a file twice, or a file and a "),
    ([Item("chair/a.png", data=b"1")], "holds no file under the folder 'lego' (its top folders: chair)"),
], ids=["twice", "file then folder", "folder then file", "no such folder"])
def test_an_archive_that_does_not_hold_one_folder_of_files_is_refused(tmp_path, kind, items, refusal):
    archive, destination = written(tmp_path, kind, items)
    with pytest.raises(DatasetError, match=re.escape(refusal)):
        unpack_folder(archive, "lego", destination)
    assert list(destination.iterdir()) == []


def test_a_file_that_is_no_archive_or_a_damaged_one_is_one_line(tmp_path):
    (destination := tmp_path / "out").mkdir()
    page = tmp_path / "page.zip"
    page.write_bytes(b"<html>Google Drive can't scan this file for viruses</html>")
    with pytest.raises(DatasetError, match=r"page.zip: not a zip or tar archive$"):
        unpack_folder(page, "lego", destination)
    data = bytearray(zip_bytes([Item("lego/transforms_train.json", data=b"{" * 4096)]))
    at = data.index(b"PK\x03\x04") + 30 + len("lego/transforms_train.json") + 10  # inside the compressed bytes
    data[at] ^= 0xFF  # a flipped byte: the member's CRC-32 (or its deflate stream) fails
    damaged = tmp_path / "damaged.zip"
    damaged.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match=r"damaged.zip: a damaged archive \("):
        unpack_folder(damaged, "lego", destination)
