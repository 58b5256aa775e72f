"""BVH motion files: hierarchy, offsets, channels in any rotation order, frame time.

The header is parsed when a file is opened; frames are then read one line at a
time, so a clip never has to be held in memory. Joint names are mapped onto the
canonical 31-bone CMU skeleton (`skeleton.CMU_BONES`): the finger-tip aliases of
the various CMU releases, and the 3dsMax-friendly naming, which lists the same
joints in the same order under other names (so it is mapped by position).

Units: BVH files carry none. CMU files use 1 unit = 1/0.45 inch = 0.056444 m
(the CMU FAQ, see the data README), the default here; pass `unit` for others.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import IO, Iterator

import numpy as np

from .kinematics import channels_to_local, forward_kinematics
from .skeleton import CMU_BONES, CMU_PARENTS, LEGS, NEEDED_BONES, SPINE, Skeleton, bone_tails, spine_by_place

CMU_UNIT_M = 0.056444

FINGER_ALIASES = {
    "LeftHandIndex1": "LeftHandFinger1", "LFingers": "LeftHandFinger1", "LeftHandFinger1": "LeftHandFinger1",
    "RightHandIndex1": "RightHandFinger1", "RFingers": "RightHandFinger1", "RightHandFinger1": "RightHandFinger1",
}
# 3dsMax-friendly CMU release, joint for joint in file order (data README, "Joint names").
MAX3DS_NAMES = {
    "LeftHip": "LeftUpLeg", "LeftKnee": "LeftLeg", "LeftAnkle": "LeftFoot", "LeftToe": "LeftToeBase",
    "RightHip": "RightUpLeg", "RightKnee": "RightLeg", "RightAnkle": "RightFoot", "RightToe": "RightToeBase",
    "lowerback": "LowerBack", "Chest": "Spine", "Chest2": "Spine1", "lowerneck": "Neck", "Neck": "Neck1",
    "LeftCollar": "LeftShoulder", "LeftShoulder": "LeftArm", "LeftElbow": "LeftForeArm", "LeftWrist": "LeftHand",
    "lhand": "LeftFingerBase", "LFingers": "LeftHandFinger1",
    "RightCollar": "RightShoulder", "RightShoulder": "RightArm", "RightElbow": "RightForeArm",
    "RightWrist": "RightHand", "rhand": "RightFingerBase", "RFingers": "RightHandFinger1",
}
_MAX3DS_MARKERS = {"LeftCollar", "RightCollar", "lowerback", "Chest2", "LeftHip", "RightHip", "lowerneck"}
# Joints a capture may leave out (they carry no captured motion in CMU data).
OPTIONAL_BONES = {"LeftToeBase", "RightToeBase", "LeftFingerBase", "RightFingerBase", "LeftHandFinger1",
                  "RightHandFinger1", "LThumb", "RThumb", "LHipJoint", "RHipJoint"}

_CHANNEL_KIND = {"Xposition": 0, "Yposition": 1, "Zposition": 2, "Xrotation": 3, "Yrotation": 4, "Zrotation": 5}


class BVHError(ValueError):
    """A malformed BVH file. The message names the file, the line and the problem."""

    def __init__(self, path, line: int | None, problem: str):
        self.path, self.line, self.problem = str(path), line, problem
        where = f"{path}:{line}" if line else f"{path}"
        super().__init__(f"{where}: {problem}")


@dataclass(frozen=True)
class BVHHeader:
    path: Path
    source_names: tuple[str, ...]  # joint names as written in the file
    skeleton: Skeleton  # canonical names, file order, rest pose (zero rotations), metres
    chan_joint: np.ndarray  # (C,) int32 joint of each channel
    chan_kind: np.ndarray  # (C,) int32 0..2 position xyz, 3..5 rotation xyz
    frame_time: float  # seconds
    n_frames: int  # as declared by `Frames:`
    unit: float  # metres per file unit
    motion_line: int  # 1-based line number of the first motion row
    cmu: bool = True  # the CMU skeleton (else another, whose bones named alike drive the character's)
    # metres taken off the root's position channels: its OFFSET where they give its place itself (`_root_shift`)
    root_shift: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def n_channels(self) -> int:
        return len(self.chan_joint)

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time


def bone_names_file(path: Path) -> Path:
    """The clip's bone-name map beside it: walk.bvh -> walk.bones.toml."""
    return path.with_suffix(".bones.toml")


def read_bone_names(path: Path) -> dict[str, str]:
    """The clip's own joint names -> the CMU names the character's bones go by, from the
    `[bones]` table of `bone_names_file(path)` ({} where there is none). BVHError naming the map
    file where it is not such a table."""
    names_path = bone_names_file(path)
    if not names_path.is_file():
        return {}
    try:
        with open(names_path, "rb") as fh:
            table = tomllib.load(fh)
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise BVHError(names_path, None, f"cannot read the bone-name map: {exc}") from None
    bones = table.get("bones")
    if not isinstance(bones, dict) or not all(isinstance(v, str) for v in bones.values()):
        raise BVHError(names_path, None, "expected a [bones] table of joint name = \"CMU bone name\" (e.g. "
                                         "pelvis = \"Hips\")")
    unknown = sorted(v for v in bones.values() if v not in CMU_BONES)
    if unknown:
        raise BVHError(names_path, None, f"[bones] maps onto {', '.join(map(repr, unknown))}, which the character "
                                         f"has no bone of (its bones: {', '.join(CMU_BONES)})")
    return dict(bones)


def plain_name(name: str) -> str:
    """A joint's name without a namespace prefix (Mixamo's `mixamorig:LeftArm` -> `LeftArm`)."""
    return name.rsplit(":", 1)[-1]


def _canonical_names(path, raw: list[tuple[str, int]], bone_names: dict[str, str]) -> tuple[list[str], bool]:
    """Each joint's name as the character's bones go by (a namespace prefix such as Mixamo's
    `mixamorig:` left off, then `bone_names`, the 3dsMax naming, the finger aliases), and whether
    every one is a CMU skeleton bone without a map: then the file is the CMU skeleton, its
    hierarchy checked against it; else another skeleton (a rig its map names), kept as it is."""
    plain = [bone_names.get(n, bone_names.get(plain_name(n), plain_name(n))) for n, _ in raw]
    max3ds = bool(_MAX3DS_MARKERS & set(plain)) and not bone_names
    out = []
    for name, (raw_name, line) in zip(plain, raw):
        canon = MAX3DS_NAMES.get(name, name) if max3ds else name
        canon = FINGER_ALIASES.get(canon, canon)
        if canon in out:
            raise BVHError(path, line, f"joint {raw_name!r} appears twice (as {canon!r})")
        out.append(canon)
    return out, all(n in CMU_BONES for n in out) and not bone_names


class _Tokens:
    """Whitespace tokens of the header with their line numbers."""

    def __init__(self, path):
        self.path = path
        self.items: list[tuple[str, int]] = []
        self.pos = 0

    def add_line(self, text: str, lineno: int) -> None:
        self.items += [(t, lineno) for t in text.split()]

    def next(self, what: str) -> tuple[str, int]:
        if self.pos >= len(self.items):
            last = self.items[-1][1] if self.items else None
            raise BVHError(self.path, last, f"file ends inside the hierarchy, expected {what}")
        tok = self.items[self.pos]
        self.pos += 1
        return tok

    def expect(self, word: str) -> int:
        tok, line = self.next(repr(word))
        if tok != word:
            raise BVHError(self.path, line, f"expected {word!r}, found {tok!r}")
        return line

    def number(self, what: str) -> float:
        tok, line = self.next(what)
        try:
            value = float(tok)
        except ValueError:
            raise BVHError(self.path, line, f"{what} is not a number: {tok!r}") from None
        if not math.isfinite(value):
            raise BVHError(self.path, line, f"{what} is not finite: {tok!r}")
        return value


def _parse_hierarchy(tokens: _Tokens, path):
    joints: list[dict] = []
    end_sites: dict[int, np.ndarray] = {}

    def parse_joint(parent: int, name: str, line: int) -> None:
        index = len(joints)
        joint = {"name": name, "line": line, "parent": parent, "offset": None, "channels": []}
        joints.append(joint)
        tokens.expect("{")
        while True:
            tok, tline = tokens.next("OFFSET, CHANNELS, JOINT, End Site or '}'")
            if tok == "OFFSET":
                joint["offset"] = [tokens.number(f"OFFSET of {name}") for _ in range(3)]
            elif tok == "CHANNELS":
                count_tok, cline = tokens.next("channel count")
                if not count_tok.isdigit():
                    raise BVHError(path, cline, f"CHANNELS count of {name} is not an integer: {count_tok!r}")
                count = int(count_tok)
                for _ in range(count):
                    ch, chl = tokens.next(f"{count} channel names for {name}")
                    if ch not in _CHANNEL_KIND:
                        raise BVHError(path, chl, f"joint {name}: CHANNELS declares {count} but "
                                                   f"{ch!r} is not a channel name")
                    joint["channels"].append(_CHANNEL_KIND[ch])
            elif tok == "JOINT":
                child, cl = tokens.next("joint name")
                parse_joint(index, child, cl)
            elif tok == "End":
                tokens.expect("Site")
                tokens.expect("{")
                tokens.expect("OFFSET")
                end_sites[index] = np.array([tokens.number("End Site OFFSET") for _ in range(3)])
                tokens.expect("}")
            elif tok == "}":
                break
            else:
                raise BVHError(path, tline, f"unexpected {tok!r} in joint {name}")
        if joint["offset"] is None:
            raise BVHError(path, line, f"joint {name} has no OFFSET")

    tok, line = tokens.next("HIERARCHY")
    if tok != "HIERARCHY":
        raise BVHError(path, line, f"expected HIERARCHY, found {tok!r}")
    tok, line = tokens.next("ROOT")
    if tok != "ROOT":
        raise BVHError(path, line, f"expected ROOT, found {tok!r}")
    name, line = tokens.next("root joint name")
    parse_joint(-1, name, line)
    if tokens.pos != len(tokens.items):
        tok, line = tokens.items[tokens.pos]
        raise BVHError(path, line, f"unexpected {tok!r} after the root joint (only one ROOT is supported)")
    return joints, end_sites


def _read_header(path: Path, fh: IO[str], unit: float) -> BVHHeader:
    tokens = _Tokens(path)
    lineno = 0
    motion_at = None
    for raw in fh:
        lineno += 1
        if raw.strip() == "MOTION":
            motion_at = lineno
            break
        tokens.add_line(raw, lineno)
    if motion_at is None:
        raise BVHError(path, lineno or None, "no MOTION section")
    joints, end_sites = _parse_hierarchy(tokens, path)

    def header_value(label: str) -> tuple[str, int]:
        nonlocal lineno
        raw = fh.readline()
        lineno += 1
        if not raw:
            raise BVHError(path, lineno, f"file ends before '{label}'")
        text = raw.strip()
        if not text.startswith(label):
            raise BVHError(path, lineno, f"expected '{label}', found {text[:40]!r}")
        return text[len(label):].strip(), lineno

    frames_text, fline = header_value("Frames:")
    try:
        n_frames = int(frames_text)
    except ValueError:
        raise BVHError(path, fline, f"Frames: is not an integer: {frames_text!r}") from None
    if n_frames < 0:
        raise BVHError(path, fline, f"Frames: is negative ({n_frames})")
    ft_text, tline = header_value("Frame Time:")
    try:
        frame_time = float(ft_text)
    except ValueError:
        raise BVHError(path, tline, f"Frame Time: is not a number: {ft_text!r}") from None
    if not (math.isfinite(frame_time) and frame_time > 0):
        raise BVHError(path, tline, f"Frame Time: must be a positive number, got {ft_text!r}")

    bone_names = read_bone_names(path)
    names, cmu = _canonical_names(path, [(j["name"], j["line"]) for j in joints], bone_names)
    parents = np.array([j["parent"] for j in joints], dtype=np.int32)
    if not cmu and not set(SPINE) & set(bone_names.values()):
        names = spine_by_place(names, parents)
    if cmu:
        for j, canon in zip(joints, names):
            parent = names[j["parent"]] if j["parent"] >= 0 else None
            want = CMU_PARENTS[canon]
            # a missing optional joint (e.g. no LHipJoint) may shift a parent one level up
            if parent != want and not (want in OPTIONAL_BONES and want not in names and CMU_PARENTS[want] == parent):
                raise BVHError(path, j["line"], f"joint {j['name']!r} is a child of {parent!r}, expected {want!r}")
        missing = [b for b in CMU_BONES if b not in names and b not in OPTIONAL_BONES]
        if missing:
            raise BVHError(path, None, f"required joints missing: {', '.join(missing)}")

    offsets = np.array([j["offset"] for j in joints], dtype=np.float64) * unit
    heads = offsets.copy()
    for b in range(len(joints)):
        if parents[b] >= 0:
            heads[b] += heads[parents[b]]
    if not cmu:
        _check_other_skeleton(path, names, parents, heads, unit)
    ends = {b: heads[b] + off * unit for b, off in end_sites.items()}
    tails = bone_tails(tuple(names), parents, heads, ends)
    chan_joint = np.array([b for b, j in enumerate(joints) for _ in j["channels"]], dtype=np.int32)
    chan_kind = np.array([k for j in joints for k in j["channels"]], dtype=np.int32)
    return BVHHeader(
        path=path,
        source_names=tuple(j["name"] for j in joints),
        skeleton=Skeleton(tuple(names), parents, heads, tails),
        chan_joint=chan_joint,
        chan_kind=chan_kind,
        frame_time=frame_time,
        n_frames=n_frames,
        unit=unit,
        motion_line=lineno + 1,
        cmu=cmu,
    )


def _check_other_skeleton(path, names: list[str], parents: np.ndarray, heads: np.ndarray, unit: float) -> None:
    """A skeleton other than CMU's drives the character through the bones it names alike: it
    needs the pelvis and both legs' chains (NEEDED_BONES, each leg's joints in descent), the
    legs hanging down along Y at rest (heads: the rest joints, m; unit: m per file unit)."""
    missing = [b for b in NEEDED_BONES if b not in names]
    if missing:
        unknown = [n for n in names if n not in CMU_BONES]
        raise BVHError(path, None, f"not the CMU skeleton (joints {', '.join(map(repr, unknown[:6]))}"
                                   f"{', ...' if len(unknown) > 6 else ''}) and no joint maps onto "
                                   f"{', '.join(missing)}, which the retargeting needs: name them in "
                                   f"{bone_names_file(Path(path)).name} (a [bones] table, e.g. pelvis = \"Hips\")")
    for side in LEGS.values():
        for upper, lower in zip(side, side[1:]):
            b, a = names.index(lower), names.index(upper)
            while b >= 0 and b != a:
                b = int(parents[b])
            if b != a:
                raise BVHError(path, None, f"joint {lower!r} does not descend from {upper!r}")
    for side in LEGS.values():
        leg = heads[names.index(side[-1])] - heads[names.index(side[0])]
        if -leg[1] < 0.5 * np.linalg.norm(leg):
            raise BVHError(path, None, f"in the rest pose {side[-1]!r} is not below {side[0]!r} along Y (the hip "
                                       f"to the ankle: {np.round(leg / unit, 3).tolist()} file units): BVH motion is "
                                       f"read Y up, as CMU's (a Z-up file needs converting)")


def _root_shift(path: Path, header: BVHHeader) -> np.ndarray:
    """Files differ on what the root's position channels give where its OFFSET is not zero: its
    place relative to the offset (the reading of the format's authors, and CMU's, whose offset is
    zero), or the place itself, the offset being the rest place repeated (Blender's and other
    exporters'). Read the first way, the second kind floats the person an offset above the floor.
    The reading that puts the first frame's lowest joint nearer the floor (y = 0) is taken: the
    offset (m) to take off the channels for the second, zeros for the first."""
    skeleton = header.skeleton
    # (the offset's components that position channels give)
    offset = skeleton.heads[0] * [np.any((header.chan_joint == 0) & (header.chan_kind == k)) for k in range(3)]
    if not np.any(offset):
        return np.zeros(3)
    with open(path, "r", encoding="utf-8", errors="replace", newline=None) as fh:
        for lineno, raw in enumerate(fh, 1):
            if lineno >= header.motion_line and raw.strip():
                break
        else:
            return np.zeros(3)  # (no frame: nothing to place)
    try:
        values = np.array(raw.split(), dtype=np.float64)
    except ValueError:
        return np.zeros(3)  # (rows() names the problem)
    if values.shape != (header.n_channels,) or not np.all(np.isfinite(values)):
        return np.zeros(3)
    n = len(skeleton.names)
    rot, pos = np.empty((n, 3, 3)), np.empty(3)
    channels_to_local(values, header.chan_joint, header.chan_kind, header.unit, rot, pos)
    g_rot, g_pos = np.empty((n, 3, 3)), np.empty((n, 3))
    forward_kinematics(skeleton.parents, skeleton.offsets, pos, rot, g_rot, g_pos)
    lowest = float(g_pos[:, 1].min())
    return offset if abs(lowest - offset[1]) < abs(lowest) else np.zeros(3)


class BVHReader:
    """Open a BVH file, parse its header, then read motion rows one at a time.

    >>> with BVHReader(path) as bvh:
    ...     for values in bvh.rows():   # (C,) channel values, file units and degrees
    ...         ...
    """

    def __init__(self, path: str | Path, unit: float = CMU_UNIT_M):
        self.path = Path(path)
        try:
            self._fh = open(self.path, "r", encoding="utf-8", errors="replace", newline=None)
        except OSError as exc:
            raise BVHError(self.path, None, f"cannot open: {exc}") from exc
        try:
            self.header = _read_header(self.path, self._fh, unit)
            self.header = replace(self.header, root_shift=_root_shift(self.path, self.header))
        except BaseException:
            self._fh.close()
            raise

    def __enter__(self) -> "BVHReader":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._fh.close()

    def rows(self) -> Iterator[np.ndarray]:
        """Yield each motion row as a float64 array, validated (count, numbers, finite)."""
        h = self.header
        count = 0
        lineno = h.motion_line - 1
        for raw in self._fh:
            lineno += 1
            text = raw.strip()
            if not text:
                continue
            if count == h.n_frames:
                raise BVHError(self.path, lineno, f"more motion rows than 'Frames: {h.n_frames}'")
            parts = text.split()
            if len(parts) != h.n_channels:
                raise BVHError(self.path, lineno,
                               f"frame {count}: expected {h.n_channels} channel values, got {len(parts)}")
            try:
                values = np.array(parts, dtype=np.float64)
            except ValueError:
                bad = next(p for p in parts if not _is_float(p))
                raise BVHError(self.path, lineno, f"frame {count}: value is not a number: {bad!r}") from None
            if not np.all(np.isfinite(values)):
                col = int(np.flatnonzero(~np.isfinite(values))[0])
                raise BVHError(self.path, lineno, f"frame {count}: channel {col} is not finite ({parts[col]})")
            count += 1
            yield values
        if count < h.n_frames:
            raise BVHError(self.path, lineno,
                           f"truncated motion: file ends after {count} of {h.n_frames} frames")


def _is_float(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def read_bvh(path: str | Path, unit: float = CMU_UNIT_M) -> tuple[BVHHeader, np.ndarray]:
    """Read a whole clip: (header, (F, C) channel values). For tests and tools; the live
    path streams with `BVHReader.rows()`."""
    with BVHReader(path, unit) as reader:
        rows = list(reader.rows())
        header = reader.header
    motion = np.array(rows, dtype=np.float64).reshape(len(rows), header.n_channels)
    return header, motion


def local_pose(header: BVHHeader, values: np.ndarray, rot_out: np.ndarray | None = None,
               pos_out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Channel values of one frame -> (local rotations (n, 3, 3), root translation (3,) metres)."""
    n = len(header.skeleton.names)
    rot = np.empty((n, 3, 3)) if rot_out is None else rot_out
    pos = np.empty(3) if pos_out is None else pos_out
    channels_to_local(values, header.chan_joint, header.chan_kind, header.unit, rot, pos)
    pos -= header.root_shift
    return rot, pos
