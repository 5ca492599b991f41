"""stablecues.fileio and stablecues.limits: untrusted text, YAML, .npy, .npz and one pickle."""

from __future__ import annotations

import io
import os
import pickle
import struct
import zipfile
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_path
from stablecues import limits
from stablecues.errors import CalibrationError, DatasetError
from stablecues.fileio import captured_stderr, load_yaml, read_npy, read_npz, read_text


class _Exec:
    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self) -> tuple:
        return (os.system, (f"touch {self.path}",))


def _header(path: Path, header: str, payload: bytes) -> Path:
    text = header.encode("latin1")
    body = text + b" " * (64 - (10 + len(text) + 1) % 64) + b"\n"
    path.write_bytes(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(body)) + body + payload)
    return path


# ---------------------------------------------------------------------------------------------
# the restricted unpickler


def test_real_vprbench_table_reads_as_numpy_does() -> None:
    path = shared_path("corridor", "ground_truth_new.npy")
    mine = read_npy(path, objects=True)
    theirs = np.load(path, allow_pickle=True)
    assert mine.shape == theirs.shape == (111, 2) and mine.dtype == object
    for a, b in zip(mine.ravel(), theirs.ravel(), strict=True):
        assert a == b if not isinstance(b, list | np.ndarray) else list(a) == list(b)


def test_tables_saved_by_this_numpy_read(tmp_path: Path) -> None:
    table = np.empty((3, 2), dtype=object)
    table[:] = [[0, [1, 2]], [1, np.array([0, 3])], [2, np.int64(1)]]
    np.save(tmp_path / "t.npy", table, allow_pickle=True)
    out = read_npy(tmp_path / "t.npy", objects=True)
    assert out[0, 1] == [1, 2] and type(out[1, 1]) is np.ndarray and out[1, 1].tolist() == [0, 3]
    assert out[2, 1] == 1


def test_a_pickle_that_would_run_a_command_is_refused(tmp_path: Path) -> None:
    canary = tmp_path / "ran"
    table = np.empty((1, 2), dtype=object)
    table[0] = [0, _Exec(canary)]
    np.save(tmp_path / "t.npy", table, allow_pickle=True)
    with pytest.raises(DatasetError, match=r"t\.npy: pickled array refused.*posix\.system"):
        read_npy(tmp_path / "t.npy", objects=True)
    assert not canary.exists()
    with pytest.raises(DatasetError, match="expected a numeric array, found Python objects"):
        read_npy(tmp_path / "t.npy")


@pytest.mark.parametrize(
    ("payload", "why"),
    [
        (b"\x80\x02cbuiltins\neval\nX\x03\x00\x00\x001+1\x85R.", "refusing builtins.eval"),
        # numpy.ndarray((10**9,), 'b') called directly: only _reconstruct may take it
        (b"\x80\x02cnumpy\nndarray\nJ\x00\xca\x9a;\x85X\x01\x00\x00\x00b\x86R.", "refused"),
        # _reconstruct asked for a huge array instead of numpy's (0,)
        (b"\x80\x02cnumpy.core.multiarray\n_reconstruct\ncnumpy\nndarray\nJ\x00\xca\x9a;\x85X\x01\x00\x00\x00b\x87R.",
         "expected \\(ndarray, \\(0,\\)"),
    ],
)
def test_other_pickles_are_refused(tmp_path: Path, payload: bytes, why: str) -> None:
    path = _header(tmp_path / "t.npy", "{'descr': '|O', 'fortran_order': False, 'shape': (1, 2), }", payload)
    with pytest.raises(DatasetError, match=why):
        read_npy(path, objects=True)


def test_array_state_larger_than_its_data_is_refused(tmp_path: Path) -> None:
    array = np.zeros((2, 2), dtype=object)
    data = bytearray(pickle.dumps(array, protocol=2))
    at = data.find(b"K\x02K\x02\x86")  # the state's shape (2, 2)
    data[at : at + 5] = b"J\x00\xe1\xf5\x05K\x02\x86"[:5]
    header = "{'descr': '|O', 'fortran_order': False, 'shape': (2, 2), }"
    path = _header(tmp_path / "t.npy", header, bytes(data))
    with pytest.raises(DatasetError, match="pickled array refused"):
        read_npy(path, objects=True)


# ---------------------------------------------------------------------------------------------
# .npy and .npz headers


def test_npy_header_claiming_more_than_the_file_holds(tmp_path: Path) -> None:
    header = "{'descr': '<f8', 'fortran_order': False, 'shape': (100000, 100000), }"
    path = _header(tmp_path / "a.npy", header, b"\0" * 64)
    with pytest.raises(DatasetError, match=r"a\.npy: \.npy header claims shape \(100000, 100000\)"):
        read_npy(path)


@pytest.mark.parametrize(
    "header",
    [
        "{'descr': '<f8', 'fortran_order': False, 'shape': ((3, 3), }",  # numpy: tokenize.TokenError
        "__import__('os').system('true')",
        "{'descr': '<f8', 'fortran_order': 'no', 'shape': (3, 3), }",
        "{'descr': 'nonsense', 'fortran_order': False, 'shape': (3, 3), }",
        "{'descr': '<f8', 'fortran_order': False, 'shape': (-3, 3), }",
    ],
)
def test_npy_malformed_headers(tmp_path: Path, header: str) -> None:
    with pytest.raises(DatasetError, match=r"a\.npy: \.npy"):
        read_npy(_header(tmp_path / "a.npy", header, b"\0" * 72))


def test_npy_reads_and_maps_what_numpy_wrote(tmp_path: Path) -> None:
    a = np.asfortranarray(np.arange(12.0).reshape(3, 4))
    np.save(tmp_path / "a.npy", a)
    np.testing.assert_array_equal(read_npy(tmp_path / "a.npy"), a)
    np.testing.assert_array_equal(read_npy(tmp_path / "a.npy", mmap=True), a)


def test_npz_member_claiming_more_than_it_holds(tmp_path: Path) -> None:
    buf = io.BytesIO()
    np.save(buf, np.zeros(4))
    member = bytearray(buf.getvalue())
    member[member.find(b"(4,)") : member.find(b"(4,)") + 4] = b"(9**9)"[:4]
    with zipfile.ZipFile(tmp_path / "a.npz", "w") as zf:
        zf.writestr("x.npy", bytes(member))
    with pytest.raises(DatasetError, match=r"a\.npz"):
        read_npz(tmp_path / "a.npz", max_bytes=1 << 20)
    np.savez(tmp_path / "b.npz", x=np.arange(3))
    assert read_npz(tmp_path / "b.npz", max_bytes=1 << 20)["x"].tolist() == [0, 1, 2]


# ---------------------------------------------------------------------------------------------
# text and YAML


def test_text_refuses_binary_and_large_files(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "a.txt").write_bytes("1 2 3\n".encode("utf-16"))
    with pytest.raises(DatasetError, match=r"a\.txt: poses: expected a UTF-8 text file, found binary data"):
        read_text(tmp_path / "a.txt", "poses")
    (tmp_path / "b.txt").write_text("x" * 100)
    with pytest.raises(CalibrationError, match=r"b\.txt: cam of 100 bytes is larger than the 10 bytes"):
        read_text(tmp_path / "b.txt", "cam", limit=10, error=CalibrationError)
    assert read_text(tmp_path / "b.txt", "cam") == "x" * 100


def test_yaml_alias_bomb_and_deep_nesting_are_refused() -> None:
    bomb = ["a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    bomb += [f"a{k}: &a{k} [" + ", ".join([f"*a{k - 1}"] * 10) + "]" for k in range(1, 9)]
    with pytest.raises(DatasetError, match="more than 100000 values once its aliases are expanded"):
        load_yaml("\n".join(bomb), "cam.yaml")
    with pytest.raises(DatasetError, match="cam.yaml: YAML nested deeper than 64 levels"):
        load_yaml("x: " + "[" * 100 + "]" * 100, "cam.yaml")
    with pytest.raises(DatasetError, match="cam.yaml: YAML nested deeper"):
        load_yaml("x: " + "[" * 20000 + "]" * 20000, "cam.yaml")
    assert load_yaml("a: &x [1, 2]\nb: *x\n", "ok.yaml") == {"a": [1, 2], "b": [1, 2]}


def test_limits_are_documented_in_one_table() -> None:
    doc = limits.__doc__ or ""
    names = [n for n in limits.__all__ if n.isupper()]
    assert names and all(f"``{n}``" in doc for n in names)
    with pytest.raises(DatasetError, match="outside the 0..40000 accepted"):
        limits.check_loop_frames(10**9, "gt.npy")


def test_what_compiled_code_prints_is_captured(capfd: pytest.CaptureFixture[str]) -> None:
    with captured_stderr(keep=20) as printed:
        for k in range(1000):
            os.write(2, f"bad header {k}\n".encode())
    assert printed.lines == ["bad header 0", "bad hea"] and printed.count == 1000  # 20 bytes kept
    os.write(2, b"after\n")
    assert capfd.readouterr().err == "after\n"  # nothing else reached the terminal
