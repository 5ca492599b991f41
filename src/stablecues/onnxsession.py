"""onnxruntime sessions of the shipped networks (segmentation, XFeat, LighterGlue): one place
for their thread count and for turning a file that does not load into one clear line.

This module imports nothing of stablecues but its errors, so that any stage may use it.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .errors import ConfigError, ModelError, reason

__all__ = ["check_graph", "default_threads", "graph_metadata", "open_session", "set_default_threads",
           "shared_session"]

_DEFAULT_THREADS = [2]
_SESSIONS: dict[tuple[str, int], Any] = {}
_LOCK = threading.Lock()


def default_threads() -> int:
    """The threads of networks loaded without a ``threads`` argument (see :func:`set_default_threads`)."""
    return _DEFAULT_THREADS[0]


def set_default_threads(threads: int) -> None:
    """The threads of networks loaded from now on without a ``threads`` argument (the
    detector's own networks among them): a worker process of a sweep sets 1, so that two
    workers on two cores do not each run two threads."""
    if int(threads) < 1:
        raise ConfigError(f"threads: expected 1 or more, got {threads}")
    _DEFAULT_THREADS[0] = int(threads)


def open_session(path: Path, what: str, threads: int | None = None) -> Any:
    """An onnxruntime CPU session of the ONNX file ``path``.

    Args:
        path: the file.
        what: what the file should hold, for messages ("segmentation graph", "XFeat graph").
        threads: intra-op threads (None: :func:`default_threads`).

    Raises:
        ModelError: the file is missing or onnxruntime cannot load it (one line naming it).
    """
    import onnxruntime as ort

    if not path.is_file():
        raise ModelError(f"{path}: {what} not found (expected an .onnx file)")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = max(1, int(default_threads() if threads is None else threads))
    opts.inter_op_num_threads = 1
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.log_severity_level = 3
    # int8 graphs (the segmentation network's int8 copy): on x86 CPUs without VNNI, onnxruntime's
    # default u8 x s8 kernel can saturate, which changed 10.6 % of CamVid val's pixels against
    # 0.3 % with this setting (pixel accuracy 86.7 % instead of 95.0 %); float graphs are unaffected
    opts.add_session_config_entry("session.x64quantprecision", "1")
    try:
        return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own untyped errors
        raise ModelError(f"{path}: expected an ONNX {what}, could not load it ({reason(exc)})") from None


def shared_session(path: Path, what: str, threads: int | None = None) -> Any:
    """:func:`open_session`, opened once per process for each file and thread count (sessions
    are safe to run from several threads)."""
    n = default_threads() if threads is None else int(threads)
    key = (str(path.resolve()) if path.exists() else str(path), n)
    with _LOCK:
        session = _SESSIONS.get(key)
        if session is None:
            session = _SESSIONS[key] = open_session(path, what, n)
    return session


def check_graph(session: Any, path: Path, what: str, inputs: Sequence[str], outputs: Sequence[str]) -> None:
    """Raise a one-line :class:`ModelError` unless the session's graph has these input and output
    names, in order (a loadable ONNX file of another network)."""
    have_in = [i.name for i in session.get_inputs()]
    have_out = [o.name for o in session.get_outputs()]
    if have_in != list(inputs) or have_out != list(outputs):
        raise ModelError(f"{path}: expected {what} (inputs {', '.join(inputs)}; outputs "
                         f"{', '.join(outputs)}), found inputs {have_in} and outputs {have_out}")


def graph_metadata(onnx_path: Path) -> dict[str, Any]:
    """The JSON an export script wrote beside an ONNX file (same stem; {} when there is none)."""
    try:
        meta = json.loads(onnx_path.with_suffix(".json").read_text())
    except (OSError, ValueError):
        return {}
    return meta if isinstance(meta, dict) else {}
