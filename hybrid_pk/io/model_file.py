"""The MODEL file: one self-contained file that ``calibrate`` writes and ``evaluate``,
``train`` and ``ik`` read.

Format (version 2): :func:`torch.save` of a plain dict, read back with
``torch.load(..., weights_only=True)`` (no pickled code is ever executed)::

    {"format": "hybrid_pk.model", "version": 2,
     "robot":   {"name", "urdf" (the URDF *text*), "urdf_path" (where it was read),
                 "end_link", "joint_names", "dtype",
                 "params": {"origin_xyz", "origin_rotvec", "axis"} (tensors)},
     "effects": [{"effect", "joint" (or None), "unit", "value" (internal tensor)}],
     "frames":  {"sets": G, "fitted": bool,
                 "base": {"T" (G, 4, 4), "T0", "dp", "rotvec"}, "tool": {...}},
     "gravity": {"vector": [gx, gy, gz] (m/s^2), "frame": "root" | "measurement"},
     "networks": opaque state of residual networks, or None,
     "metadata": {..., "created": {"time", "hybrid_pk", "torch"}}}

``base.T`` / ``tool.T`` are the frames as matrices (``T_meas_root``, ``T_end_point``);
``T0, dp, rotvec`` are the exact parameter state, so a loaded model reproduces the
saved one's ``forward`` bit for bit.

``gravity`` is the mounting the statics use (version 2; a version-1 file has none and
means a robot upright on the floor, which is how such a file is still written, so that
an older hybrid_pk reads it right).

``nominal:ROBOT`` in place of a file gives the URDF as it is, with identity frames.
"""

from __future__ import annotations

import datetime as _dt
import os
import zipfile
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from hybrid_pk.effects import ExtendedModel, Gravity, entry_label, make_effect
from hybrid_pk.errors import HybridPKError, ModelFileError, RobotModelError
from hybrid_pk.output_file import replacing
from hybrid_pk.robot import Robot, load_chain_spec, resolve_urdf
from hybrid_pk.robot.urdf_copy import urdf_copy

__all__ = [
    "FORMAT_TAG",
    "FORMAT_VERSION",
    "NOMINAL_PREFIX",
    "LoadedModel",
    "load_model",
    "model_robot",
    "save_model",
]

FORMAT_TAG = "hybrid_pk.model"
FORMAT_VERSION = 2  # 2: the mounting ("gravity"); 1: upright only
NOMINAL_PREFIX = "nominal:"
_ROBOT_PARAMS = ("origin_xyz", "origin_rotvec", "axis")
_FRAME_STATE = ("T0", "dp", "rotvec")
_DTYPES = {"float64": torch.float64, "float32": torch.float32}


@dataclass(frozen=True)
class LoadedModel:
    """What :func:`load_model` returns.

    Attributes:
        model: the extended model (robot, effects, base and tool frames).
        networks: opaque state of the residual networks, exactly as saved; None if none.
        metadata: free-form information saved with the model (incl. ``"created"``).
        robot_name: the URDF's robot name.
        frames_fitted: False when the base/tool frames were never fitted (identity).
        source: the file path, or ``"nominal:ROBOT"``.
    """

    model: ExtendedModel
    networks: dict | None
    metadata: dict = field(default_factory=dict)
    robot_name: str = ""
    frames_fitted: bool = True
    source: str = ""

    @property
    def has_networks(self) -> bool:
        return bool(self.networks)


def model_robot(loaded: LoadedModel) -> Robot:
    """The robot of a loaded model (URDF rebuilt from the file's own copy)."""
    return loaded.model.robot


# ----------------------------------------------------------------------------- saving


def _check_plain(value: Any, where: str) -> None:
    """Refuse what ``torch.load(weights_only=True)`` could not read back (exact types:
    a ``str`` or ``float`` subclass such as ``numpy.float64`` pickles as its class)."""
    if value is None or type(value) in (str, bool, int, float) or isinstance(value, Tensor):
        return
    if type(value) in (dict, OrderedDict):
        for k, v in value.items():
            if type(k) not in (str, int):
                raise ModelFileError(f"{where}: keys must be str or int, found {type(k).__name__}")
            _check_plain(v, f"{where}[{k!r}]")
        return
    if type(value) in (list, tuple):
        for i, v in enumerate(value):
            _check_plain(v, f"{where}[{i}]")
        return
    raise ModelFileError(
        f"{where}: cannot store a {type(value).__name__} in a model file; use tensors, "
        "Python numbers, strings, lists and dicts (e.g. a module's state_dict())"
    )


def _frame_state(frame) -> dict[str, Tensor]:
    state = {name: getattr(frame, name).detach().cpu().clone() for name in _FRAME_STATE}
    state["T"] = frame.matrix().detach().cpu().clone()
    return state


def save_model(
    path: str | os.PathLike,
    model: ExtendedModel,
    *,
    networks: dict | None = None,
    metadata: dict | None = None,
    frames_fitted: bool = True,
) -> Path:
    """Write ``model`` (and residual-network state) to one self-contained file.

    Args:
        path: output file (any suffix; ``.pt`` is customary). Written atomically.
        model: robot + effects + base/tool frames.
        networks: state of residual networks (tensors, numbers, strings, lists, dicts),
            stored and returned by :func:`load_model` as is.
        metadata: free-form JSON-like information (fit summary, data files, ...).
        frames_fitted: whether the base/tool frames were estimated (False: identity).

    Raises:
        ModelFileError: if the robot's URDF cannot be read or an entry is not storable.
    """
    if not isinstance(model, ExtendedModel):  # a Robot: hpk.ExtendedModel(robot) wraps it
        raise HybridPKError(f"save_model needs an ExtendedModel, got {type(model).__name__}")
    path = Path(path)
    robot = model.robot
    spec = robot.spec
    try:
        urdf_text = Path(spec.urdf_path).read_text(encoding="utf-8")
    except OSError as exc:
        raise ModelFileError(
            f"cannot save the model: its URDF {spec.urdf_path} is not readable ({exc})"
        ) from exc
    meta = dict(metadata or {})
    meta["created"] = {
        "time": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "hybrid_pk": _version(),
        "torch": str(torch.__version__),
    }
    if networks is not None:
        _check_plain(networks, "networks")
    _check_plain(meta, "metadata")
    payload = {
        "format": FORMAT_TAG,
        "version": 1 if model.gravity.is_default else FORMAT_VERSION,
        "robot": {
            "name": spec.name,
            "urdf": urdf_text,
            "urdf_path": str(spec.urdf_path),
            "end_link": spec.end_link,
            "joint_names": list(spec.joint_names),
            "dtype": str(robot.dtype).removeprefix("torch."),
            "params": {n: getattr(robot, n).detach().cpu().clone() for n in _ROBOT_PARAMS},
        },
        "effects": [
            {
                "effect": e.kind,
                "joint": e.joint,
                "unit": e.unit,
                "value": e.value.detach().cpu().clone(),
            }
            for e in model.effects
        ],
        "frames": {
            "sets": model.base.sets,
            "fitted": bool(frames_fitted),
            "base": _frame_state(model.base),
            "tool": _frame_state(model.tool),
        },
        "networks": networks,
        "metadata": meta,
    }
    if not model.gravity.is_default:
        payload["gravity"] = model.gravity.to_dict()
    with replacing(path) as tmp:
        try:
            torch.save(payload, tmp)
        except RuntimeError:  # torch's zip writer reports a failed write so
            raise OSError("torch.save could not write the model's data") from None
    return path


def _version() -> str:
    from hybrid_pk import __version__

    return __version__


# ----------------------------------------------------------------------------- loading


def _robot_identity(robot_check: str | Sequence[str], end_link: str | None):
    """``(name, joint_names)`` a check asks for; either may be None (not checked)."""
    if not isinstance(robot_check, str):
        return None, tuple(robot_check)
    try:
        path = resolve_urdf(robot_check)
    except RobotModelError:
        return robot_check, None  # a bare robot name: compare names only
    for end in (end_link, None):  # the model's end link may not exist there: joints differ
        try:
            spec = load_chain_spec(path, end)
        except RobotModelError:
            continue
        return spec.name, spec.joint_names
    return robot_check, None  # an unusable URDF: it cannot be the model's robot by name


def _check_robot(
    source: str,
    name: str,
    joints: Sequence[str],
    end_link: str | None,
    robot_check: str | Sequence[str] | None,
) -> None:
    if robot_check is None:
        return
    want_name, want_joints = _robot_identity(robot_check, end_link)
    bad_name = want_name is not None and want_name != name
    bad_joints = want_joints is not None and tuple(want_joints) != tuple(joints)
    if not (bad_name or bad_joints):
        return
    if isinstance(robot_check, str):
        wanted = repr(want_name if want_name is not None else robot_check)
        if bad_joints and not bad_name:
            wanted += f" (joints {', '.join(want_joints)})"
    else:
        wanted = f"joints {', '.join(robot_check)}"
    what = "model" if source.startswith(NOMINAL_PREFIX) else "model file"
    raise ModelFileError(
        f"{what} {source} was made for robot {name!r} (joints {', '.join(joints)}), not {wanted}"
    )


def _urdf_file(text: str, original: str, name: str) -> Path:
    """A file holding ``text``: the original path if unchanged, else a private copy."""
    try:
        if Path(original).read_text(encoding="utf-8") == text:
            return Path(original)
    except (OSError, ValueError):
        pass
    return urdf_copy(text, name)


def _load_nominal(spec: str, robot_check, end_link: str | None) -> LoadedModel:
    name = spec[len(NOMINAL_PREFIX) :]
    if not name:
        raise ModelFileError("nominal: needs a robot, e.g. nominal:rx160 or nominal:my.urdf")
    robot = Robot.from_urdf(name, end_link=end_link)
    _check_robot(spec, robot.name, robot.joint_names, robot.end_link, robot_check)
    return LoadedModel(
        model=ExtendedModel(robot),
        networks=None,
        metadata={},
        robot_name=robot.name,
        frames_fitted=False,
        source=spec,
    )


def _read_payload(path: Path) -> dict:
    if path.is_dir():
        raise ModelFileError(f"model file {path} is a directory")
    if not path.is_file():
        hint = ""
        if not path.suffix and not path.parent.parts:
            hint = f" (for the URDF as it is, write nominal:{path})"
        raise ModelFileError(f"model file not found: {path}{hint}")
    if path.suffix.lower() == ".urdf":
        raise ModelFileError(
            f"{path} is a URDF, not a hybrid_pk model file; write nominal:{path} to use the "
            "URDF as it is"
        )
    if path.stat().st_size == 0 or not zipfile.is_zipfile(path):  # torch.save writes a zip
        what = "it is empty" if path.stat().st_size == 0 else "it is not a torch archive"
        raise ModelFileError(
            f"{path} is not a hybrid_pk model file ({what}); model files are written by "
            "'hybrid-pk calibrate' or 'hybrid-pk train'"
        )
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises UnpicklingError, RuntimeError, EOFError, ...
        reason = " ".join(str(exc).split())[:160]
        if "weights only load failed" in reason.lower():
            reason = "it holds Python objects besides tensors and plain data"
        raise ModelFileError(
            f"{path} is not a hybrid_pk model file (cannot be read as one: {reason})"
        ) from exc
    if not isinstance(payload, dict) or payload.get("format") != FORMAT_TAG:
        raise ModelFileError(
            f"{path} is not a hybrid_pk model file (no {FORMAT_TAG!r} format tag); "
            "model files are written by 'hybrid-pk calibrate' or 'hybrid-pk train'"
        )
    version = payload.get("version")
    if not isinstance(version, int) or version < 1:
        raise ModelFileError(f"{path}: corrupt hybrid_pk model file (format version {version!r})")
    if version > FORMAT_VERSION:
        raise ModelFileError(
            f"{path} has model-file format version {version}, this hybrid_pk "
            f"({_version()}) reads up to version {FORMAT_VERSION}: upgrade hybrid_pk"
        )
    return payload


def _restore_frame(frame, state: dict) -> None:
    with torch.no_grad():
        if all(k in state for k in _FRAME_STATE):
            for k in _FRAME_STATE:
                getattr(frame, k).copy_(state[k])
        else:
            frame.reset_to(state["T"])


def _build(path: Path, payload: dict, robot_check, end_link: str | None) -> LoadedModel:
    info = payload["robot"]
    name, joints, end = info["name"], tuple(info["joint_names"]), info["end_link"]
    _check_robot(str(path), name, joints, end, robot_check)
    if end_link is not None and end_link != end:
        raise ModelFileError(f"model file {path} ends at link {end!r}, not {end_link!r}")
    dtype = _DTYPES.get(info.get("dtype", "float64"))
    if dtype is None:
        raise ModelFileError(f"{path}: unsupported dtype {info.get('dtype')!r}")
    urdf = _urdf_file(info["urdf"], info.get("urdf_path", ""), name)
    try:
        robot = Robot.from_urdf(urdf, end_link=end, dtype=dtype)
    except RobotModelError as exc:
        raise ModelFileError(f"{path}: its stored URDF cannot be used: {exc}") from exc
    if tuple(robot.joint_names) != joints:
        raise ModelFileError(
            f"{path}: corrupt model file (stored joints {list(joints)}, URDF gives "
            f"{robot.joint_names})"
        )
    with torch.no_grad():
        for n in _ROBOT_PARAMS:
            if n in info.get("params", {}):
                getattr(robot, n).copy_(info["params"][n])
    effects = []
    for entry in payload["effects"]:
        effects.append(make_effect(robot, entry_label(entry), entry["value"]))
    frames = payload["frames"]
    try:
        gravity = Gravity.from_dict(payload.get("gravity"))
    except HybridPKError as exc:
        raise ModelFileError(f"{path}: corrupt gravity entry ({exc})") from exc
    model = ExtendedModel(robot, effects, frame_sets=int(frames["sets"]), gravity=gravity)
    _restore_frame(model.base, frames["base"])
    _restore_frame(model.tool, frames["tool"])
    return LoadedModel(
        model=model,
        networks=payload.get("networks"),
        metadata=dict(payload.get("metadata") or {}),
        robot_name=name,
        frames_fitted=bool(frames.get("fitted", True)),
        source=str(path),
    )


def load_model(
    path_or_spec: str | os.PathLike,
    *,
    robot_check: str | Sequence[str] | None = None,
    end_link: str | None = None,
) -> LoadedModel:
    """Read a model file, or build ``nominal:ROBOT`` (URDF as it is, identity frames).

    Args:
        path_or_spec: model file path, or ``"nominal:ROBOT"`` (shipped name or URDF path).
        robot_check: robot name / URDF path, or joint-name list, the model must be for.
        end_link: end link of a ``nominal:`` robot (default the URDF's leaf); for a file,
            it must match the stored one.

    Raises:
        ModelFileError: missing file, not a model file, newer format version, a corrupt
            file, or a model made for another robot than ``robot_check``.
    """
    spec = os.fspath(path_or_spec)
    if spec.startswith(NOMINAL_PREFIX):
        return _load_nominal(spec, robot_check, end_link)
    path = Path(spec)
    payload = _read_payload(path)
    try:
        return _build(path, payload, robot_check, end_link)
    except (KeyError, TypeError, IndexError, RuntimeError) as exc:
        raise ModelFileError(
            f"{path}: corrupt hybrid_pk model file ({type(exc).__name__}: {exc})"
        ) from exc
