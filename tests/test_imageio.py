"""stablecues.imageio: every read mode on small images written in the test, files that must fail
naming themselves, listing in natural order, matching by stem, depth and label images."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from stablecues.errors import DatasetError, ImageError, InputError
from stablecues.imageio import (
    IMAGE_SUFFIXES,
    is_image_file,
    list_images,
    match_by_stem,
    natural_key,
    read_depth,
    read_image,
    read_labels,
    to_grey,
)

BGR = (10, 20, 30)  # blue, green, red


def _write(path: Path, image: np.ndarray) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), image)
    return path


@pytest.fixture
def grey_png(tmp_path: Path) -> Path:
    return _write(tmp_path / "grey.png", np.arange(12, dtype=np.uint8).reshape(3, 4) * 20)


@pytest.fixture
def colour_png(tmp_path: Path) -> Path:
    return _write(tmp_path / "colour.png", np.full((3, 4, 3), BGR, np.uint8))


@pytest.fixture
def png16(tmp_path: Path) -> Path:
    return _write(tmp_path / "depth16.png", np.array([[0, 0x1234], [65535, 256]], np.uint16))


@pytest.fixture
def rgba_png(tmp_path: Path) -> Path:
    return _write(tmp_path / "rgba.png", np.full((3, 4, 4), (*BGR, 128), np.uint8))


# ----------------------------------------------------------------------------------------------
# read modes


def test_grey_file_in_every_mode(grey_png: Path) -> None:
    stored = np.arange(12, dtype=np.uint8).reshape(3, 4) * 20
    for mode in ("grey", "unchanged", "8bit", "8bit-grey"):
        image = read_image(grey_png, mode)
        assert image.dtype == np.uint8
        np.testing.assert_array_equal(image, stored, err_msg=mode)
    for mode in ("bgr", "rgb"):
        image = read_image(grey_png, mode)
        assert image.shape == (3, 4, 3) and image.dtype == np.uint8
        np.testing.assert_array_equal(image, np.dstack([stored] * 3), err_msg=mode)
    np.testing.assert_array_equal(read_image(grey_png), read_image(grey_png, "bgr"))  # the default


def test_colour_file_in_every_mode(colour_png: Path) -> None:
    bgr = read_image(colour_png, "bgr")
    assert bgr.shape == (3, 4, 3) and tuple(bgr[0, 0]) == BGR
    assert tuple(read_image(colour_png, "rgb")[0, 0]) == BGR[::-1]
    assert tuple(read_image(colour_png, "unchanged")[2, 3]) == BGR
    np.testing.assert_array_equal(read_image(colour_png, "8bit"), bgr)
    expected_grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    np.testing.assert_array_equal(read_image(colour_png, "8bit-grey"), expected_grey)
    codec_grey = read_image(colour_png, "grey")  # decoded to grey by the codec: may round differently
    assert codec_grey.shape == (3, 4) and abs(int(codec_grey[0, 0]) - int(expected_grey[0, 0])) <= 1


def test_16bit_file(png16: Path) -> None:
    raw = read_image(png16, "unchanged")
    assert raw.dtype == np.uint16 and raw.tolist() == [[0, 0x1234], [65535, 256]]
    for mode in ("8bit", "8bit-grey"):  # scaled down by >> 8
        image = read_image(png16, mode)
        assert image.dtype == np.uint8 and image.tolist() == [[0, 0x12], [255, 1]], mode
    assert read_image(png16, "bgr").shape == (2, 2, 3) and read_image(png16, "bgr").dtype == np.uint8
    assert read_image(png16, "grey").shape == (2, 2) and read_image(png16, "grey").dtype == np.uint8


def test_rgba_file(rgba_png: Path) -> None:
    raw = read_image(rgba_png, "unchanged")
    assert raw.shape == (3, 4, 4) and tuple(raw[0, 0]) == (*BGR, 128)
    eight = read_image(rgba_png, "8bit")  # alpha dropped, colour kept
    assert eight.shape == (3, 4, 3) and tuple(eight[1, 1]) == BGR
    grey = read_image(rgba_png, "8bit-grey")
    np.testing.assert_array_equal(grey, cv2.cvtColor(eight, cv2.COLOR_BGR2GRAY))
    assert read_image(rgba_png, "bgr").shape == (3, 4, 3)


def test_float_file_is_not_8bit(tmp_path: Path) -> None:
    path = _write(tmp_path / "f.tiff", np.full((2, 3), 1.5, np.float32))
    assert read_image(path, "unchanged").dtype == np.float32
    with pytest.raises(ImageError, match=r"f.tiff: expected an 8-bit image, found dtype float32"):
        read_image(path, "8bit")


def test_unknown_mode(grey_png: Path) -> None:
    with pytest.raises(InputError, match="image mode 'colour': expected one of bgr, rgb, grey"):
        read_image(grey_png, "colour")  # type: ignore[arg-type]


# ----------------------------------------------------------------------------------------------
# files that cannot be read


def test_missing_empty_and_corrupt_files_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(ImageError, match="absent.png: image file not found") as info:
        read_image(tmp_path / "absent.png")
    assert isinstance(info.value, DatasetError) and isinstance(info.value, InputError)
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(ImageError, match=r"empty.png: not a readable image \(the file is empty\)"):
        read_image(tmp_path / "empty.png", "unchanged")
    (tmp_path / "a.gif").write_bytes(b"GIF89a" + b"\0" * 20)
    with pytest.raises(ImageError, match=r"a.gif: not a readable image \(expected a PNG, JPEG, BMP"):
        read_image(tmp_path / "a.gif")
    (tmp_path / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 10)
    with pytest.raises(ImageError, match="corrupt.png: not a readable image"):
        read_image(tmp_path / "corrupt.png", "8bit")
    (tmp_path / "folder.png").mkdir()
    with pytest.raises(ImageError, match="folder.png: image file not found"):
        read_image(tmp_path / "folder.png")
    with pytest.raises(ImageError, match="absent.png: image file not found"):
        read_depth(tmp_path / "absent.png", 1000.0)
    with pytest.raises(ImageError, match="corrupt.png: not a readable image"):
        read_labels(tmp_path / "corrupt.png")


def test_what_the_codecs_print_goes_into_the_error(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    ok, buf = cv2.imencode(".png", np.zeros((8, 8), np.uint8))
    data = bytearray(buf.tobytes())
    data[41:45] = b"\xff\xff\xff\xff"  # the IDAT payload: libpng complains on stderr
    (tmp_path / "bad.png").write_bytes(bytes(data))
    with pytest.raises(ImageError, match=r"bad\.png: not a readable image \(a corrupt PNG file"):
        read_image(tmp_path / "bad.png")
    assert capfd.readouterr().err == ""  # nothing reached the terminal


def test_a_png_chunk_longer_than_the_file_is_refused(tmp_path: Path) -> None:
    """An 84-byte PNG whose IDAT declares 3.5 GB made OpenCV allocate them."""
    ok, buf = cv2.imencode(".png", np.zeros((8, 8), np.uint8))
    data = bytearray(buf.tobytes())
    data[33] = 0xD5  # the IDAT chunk's length, high byte
    (tmp_path / "a.png").write_bytes(bytes(data))
    with pytest.raises(ImageError, match=r"a\.png: not a readable image \(a damaged PNG header\)"):
        read_image(tmp_path / "a.png")


# ----------------------------------------------------------------------------------------------
# depth and labels


def test_read_depth_zeros_become_nan_and_factor(png16: Path, tmp_path: Path) -> None:
    depth = read_depth(png16, 5000.0)
    assert depth.dtype == np.float32 and np.isnan(depth[0, 0])
    np.testing.assert_allclose(depth[0, 1], 0x1234 / 5000.0, rtol=1e-6)
    np.testing.assert_allclose(depth[1], [65535 / 5000.0, 256 / 5000.0], rtol=1e-6)
    np.testing.assert_allclose(read_depth(png16, 1.0)[1, 1], 256.0)
    metres = _write(tmp_path / "m.tiff", np.array([[0.0, 2.5], [np.nan, 1.0]], np.float32))
    depth = read_depth(metres, 5000.0)  # a float file is already metres: not divided
    assert np.isnan(depth[0, 0]) and np.isnan(depth[1, 0]) and depth[0, 1] == 2.5 and depth[1, 1] == 1.0


def test_read_depth_rejects_colour(colour_png: Path) -> None:
    with pytest.raises(
        ImageError, match=r"colour.png: expected a single-channel depth image, found shape \(3, 4, 3\)"
    ):
        read_depth(colour_png, 1000.0)


def test_read_labels(grey_png: Path, colour_png: Path, png16: Path) -> None:
    labels = read_labels(grey_png)
    assert labels.dtype == np.uint8 and labels.shape == (3, 4) and labels[0, 1] == 20
    with pytest.raises(
        ImageError,
        match=r"colour.png: expected a single-channel uint8 label image, found shape \(3, 4, 3\) uint8",
    ):
        read_labels(colour_png)
    with pytest.raises(ImageError, match=r"found shape \(2, 2\) uint16"):
        read_labels(png16)


def test_to_grey() -> None:
    bgr = np.full((2, 3, 3), BGR, np.uint8)
    np.testing.assert_array_equal(to_grey(bgr), cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
    bgra = np.dstack([bgr, np.full((2, 3), 7, np.uint8)])
    np.testing.assert_array_equal(to_grey(bgra), to_grey(bgr))
    grey = np.zeros((2, 3), np.uint8)
    assert to_grey(grey) is grey and to_grey(grey[:, :, None]).shape == (2, 3)
    with pytest.raises(InputError, match="left: expected dtype uint8, got float32"):
        to_grey(grey.astype(np.float32), "left")
    with pytest.raises(InputError, match="expected shape HxW or HxWxC"):
        to_grey(np.zeros((2, 3, 2), np.uint8))
    with pytest.raises(InputError, match="expected a numpy array, got list"):
        to_grey([[0]])  # type: ignore[arg-type]


# ----------------------------------------------------------------------------------------------
# listing and matching


def test_list_images_natural_order(tmp_path: Path) -> None:
    for name in ("10.png", "2.png", "1.png", "b.JPG", "a.jpeg", "notes.txt"):
        (tmp_path / name).write_bytes(b"x")  # listing reads no pixels
    (tmp_path / "sub.png").mkdir()  # a folder, whatever its name
    names = [p.name for p in list_images(tmp_path)]
    assert names == ["1.png", "2.png", "10.png", "a.jpeg", "b.JPG"]
    assert [p.name for p in list_images(tmp_path, suffixes=(".jpg",))] == ["b.JPG"]
    assert is_image_file(tmp_path / "b.JPG") and not is_image_file(tmp_path / "notes.txt")
    assert not is_image_file(tmp_path / "sub.png") and ".png" in IMAGE_SUFFIXES


def test_natural_key_is_total() -> None:
    names = ["img10.png", "img2.png", "img02.png", "img1.png"]
    assert sorted(names, key=natural_key) == ["img1.png", "img02.png", "img2.png", "img10.png"]
    mixed = ["b.png", "B.png", "a.png", "A.png"]
    ordered = sorted(mixed, key=natural_key)
    assert ordered == ["A.png", "a.png", "B.png", "b.png"]  # case only breaks ties
    assert sorted(reversed(mixed), key=natural_key) == ordered  # whatever the input order
    # case and leading zeros decide only between names that are otherwise equal
    assert sorted(["Img2.png", "img1.png"], key=natural_key) == ["img1.png", "Img2.png"]
    assert sorted(["a01b2", "a1b1"], key=natural_key) == ["a1b1", "a01b2"]


def test_list_images_recursive_and_empty(tmp_path: Path) -> None:
    for rel in ("b/1.png", "a/10.png", "a/2.png", "top.png"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_bytes(b"x")
    assert [p.name for p in list_images(tmp_path)] == ["top.png"]
    rels = [p.relative_to(tmp_path).as_posix() for p in list_images(tmp_path, recursive=True)]
    assert rels == ["a/2.png", "a/10.png", "b/1.png", "top.png"]
    empty = tmp_path / "empty"
    empty.mkdir()
    assert list_images(empty, allow_empty=True) == []
    with pytest.raises(ImageError, match=r"empty: expected image files \(.png, .jpg, .*\), found none"):
        list_images(empty)
    with pytest.raises(ImageError, match="absent: left images folder not found"):
        list_images(tmp_path / "absent", "left images")
    with pytest.raises(ImageError, match="folder not found"):
        list_images(tmp_path / "absent", allow_empty=True)


def test_match_by_stem(tmp_path: Path) -> None:
    left = [tmp_path / "left" / f"{k}.png" for k in (1, 2)]
    right = tmp_path / "right"
    right.mkdir()
    (right / "1.jpg").write_bytes(b"x")  # any image suffix
    (right / "2.PNG").write_bytes(b"x")
    (right / "2.txt").write_bytes(b"x")
    assert match_by_stem(left, right, "right") == [right / "1.jpg", right / "2.PNG"]
    (right / "2.PNG").unlink()
    with pytest.raises(ImageError, match=r"right: expected a right image named 2\.\*, found none"):
        match_by_stem(left, right, "right")
    assert match_by_stem([], right, "right") == []


@pytest.mark.parametrize("ext", [".png", ".jpg", ".bmp", ".ppm", ".pgm", ".tif", ".webp"])
def test_header_size_of_every_format(ext: str) -> None:
    from stablecues.imageio import header_size

    image = np.zeros((37, 53), np.uint8) if ext == ".pgm" else np.zeros((37, 53, 3), np.uint8)
    ok, buf = cv2.imencode(ext, image)
    assert ok and header_size(buf.tobytes()) == (53, 37)
    assert header_size(b"not an image") is None and header_size(b"\x89PNG\r\n\x1a\n") is None


def test_an_image_too_large_is_refused_before_it_is_decoded(tmp_path: Path) -> None:
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", 65535, 65535, 8, 0, 0, 0, 0)  # the header claims 4.3 Gpx
    (tmp_path / "big.png").write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IEND", b""))
    with pytest.raises(ImageError, match=r"big\.png: a 65535 x 65535 image is larger than the 67108864"):
        read_image(tmp_path / "big.png")
    cv2.imwrite(str(tmp_path / "small.png"), np.zeros((20, 30), np.uint8))
    with pytest.raises(ImageError, match=r"small\.png: a 30 x 20 image is larger than the 100 pixels"):
        read_image(tmp_path / "small.png", max_pixels=100)


def test_a_png_decoding_past_the_byte_limit_is_refused_from_its_header(tmp_path: Path) -> None:
    """Issue 34: under the pixel limit, a 16-bit RGBA 8192 x 8191 PNG (8 bytes a pixel) of 1 MB
    decoded to 1.7 GB; its header says so before anything is decoded. The same size in 8-bit
    grey passes the check."""
    import struct
    import zlib

    from stablecues.imageio import check_decoded_bytes

    def png(depth: int, colour: int) -> bytes:
        def chunk(kind: bytes, data: bytes) -> bytes:
            return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

        ihdr = struct.pack(">IIBBBBB", 8192, 8191, depth, colour, 0, 0, 0)
        idat = chunk(b"IDAT", zlib.compress(b"\0" * 64))
        return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + idat + chunk(b"IEND", b"")

    path = tmp_path / "big.png"
    path.write_bytes(png(16, 6))
    with pytest.raises(ImageError, match=r"8192 x 8191 PNG of 8 bytes a pixel decodes to 511 MiB, more than"):
        read_image(path)
    check_decoded_bytes(path, png(8, 0), (8192, 8191))  # 64 MiB: within the limit
