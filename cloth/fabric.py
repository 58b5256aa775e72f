"""Fabric materials as data: presets in fabrics.toml, user files with the same keys."""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, fields
from pathlib import Path

PRESETS_PATH = Path(__file__).with_name("fabrics.toml")


class FabricError(ValueError):
    """A fabric file or table is malformed; the message names the file, fabric and key."""


@dataclass(frozen=True)
class Fabric:
    name: str
    stretch_stiffness: float  # N/m, spring longer than rest
    compression_stiffness: float  # N/m, spring shorter than rest
    shear_stiffness: float  # N/m
    bending_stiffness: float  # N/m
    damping_ratio: float  # fraction of critical
    density: float  # kg/m²
    friction: float  # Coulomb coefficient
    air_drag: float  # N·s/m³
    thickness: float  # m
    max_strain: float  # structural springs are capped at (1 + max_strain) * rest length
    # detailed surface (S104-S106)
    k_out_plane: float  # m/(N·s): how fast a particle moves along its normal per unit normal force
    h_normal: float  # m: height at which the shading normal is fully the deformed surface's
    max_neighbour_ratio: float  # detailed neighbours at most this times their rest distance apart
    transfer_exponent: float  # force transfer rate along the surface: max(cos θ, 0) ** exponent


_KEYS = [f.name for f in fields(Fabric) if f.name != "name"]
_POSITIVE = {"stretch_stiffness", "density", "h_normal", "max_neighbour_ratio"}


def fabric_from_table(name: str, table: dict, source: str = "<table>") -> Fabric:
    unknown = set(table) - set(_KEYS)
    if unknown:
        raise FabricError(f"{source}: [{name}]: unknown key(s) {sorted(unknown)}; known: {_KEYS}")
    missing = [k for k in _KEYS if k not in table]
    if missing:
        raise FabricError(f"{source}: [{name}]: missing key(s) {missing}")
    values = {}
    for k in _KEYS:
        v = table[k]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise FabricError(f"{source}: [{name}].{k}: expected a finite number, got {v!r}")
        if v < 0 or (k in _POSITIVE and v == 0):
            raise FabricError(f"{source}: [{name}].{k}: must be {'> 0' if k in _POSITIVE else '>= 0'}, got {v}")
        values[k] = float(v)
    if values["compression_stiffness"] > values["stretch_stiffness"]:
        raise FabricError(f"{source}: [{name}]: compression_stiffness must not exceed stretch_stiffness "
                          "(cloth resists stretch, not compression)")
    if values["max_neighbour_ratio"] < 1.0:
        raise FabricError(f"{source}: [{name}].max_neighbour_ratio: must be >= 1 (rest distances must be allowed), "
                          f"got {values['max_neighbour_ratio']}")
    return Fabric(name=name, **values)


def _read_toml(path: Path) -> dict:
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise FabricError(f"{path}: cannot read: {exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise FabricError(f"{path}: not valid TOML: {exc}") from exc


def load_fabrics(path: str | Path = PRESETS_PATH) -> dict[str, Fabric]:
    path = Path(path)
    data = _read_toml(path)
    out = {}
    for name, table in data.items():
        if not isinstance(table, dict):
            raise FabricError(f"{path}: {name!r} must be a table [{name}]")
        out[name] = fabric_from_table(name, table, str(path))
    return out


def fabric(name: str, path: str | Path | None = None) -> Fabric:
    """A preset by name (or a fabric from a user file)."""
    table = load_fabrics(path or PRESETS_PATH)
    if name not in table:
        raise FabricError(f"{path or PRESETS_PATH}: no fabric {name!r}; available: {sorted(table)}")
    return table[name]


def fabric_choice(text: str, path: str | Path | None = None) -> Fabric | dict[str, Fabric]:
    """What `--fabric` (and an outfit request's "fabric") names: one fabric for every garment (a
    preset's name, or one from the file `path`), or one per garment, `garment=fabric` pairs
    separated by commas ("top=silk,bottom=denim"; a garment by its name, or the part of it after
    its outfit's name: `garment_fabrics`), the garments it does not name keeping theirs.
    FabricError naming the pair and the problem."""
    text = str(text).strip()
    if "=" not in text:
        return fabric(text, path)
    out: dict[str, Fabric] = {}
    for pair in text.split(","):
        garment, sep, name = (part.strip() for part in pair.partition("="))
        if not sep or not garment or not name:
            raise FabricError(f"fabric choice {text!r}: {pair.strip()!r} is not garment=fabric "
                              f'(e.g. "top=silk,bottom=denim", or one fabric for every garment: "denim")')
        if garment in out:
            raise FabricError(f"fabric choice {text!r}: garment {garment!r} is named twice")
        try:
            out[garment] = fabric(name, path)
        except FabricError as err:
            raise FabricError(f"fabric choice {text!r}: {garment}={name}: {err}") from None
    return out


def garment_fabrics(choice: dict[str, Fabric], names: list[str]) -> dict[str, Fabric]:
    """A per-garment choice (`fabric_choice`) keyed by the outfit's garment names: a key is a
    garment's name, or what follows its outfit's name and a dot ("top" for
    "female_casualsuit01.top"). FabricError naming a key no garment answers to, and the names."""
    out = {}
    for key, fab in choice.items():
        hits = [n for n in names if n == key] or [n for n in names if n.rsplit(".", 1)[-1] == key]
        if len(hits) != 1:
            raise FabricError(f"fabric choice: no garment {key!r} in the outfit; it has {names}" if not hits else
                              f"fabric choice: {key!r} names several garments {hits}; give the whole name")
        out[hits[0]] = fab
    return out


OUTFIT_FABRICS = "fabrics.toml"  # in an outfit's folder: which fabric each of its garments is made of


def outfit_fabrics(path: str | Path) -> dict[str, Fabric]:
    """The fabric of each garment of an outfit, from its folder's fabrics.toml: a table
    `[garments]` naming each garment's fabric (`jeans = "denim"`), a preset's or one the same file
    defines in a table of its own with the preset keys. FabricError naming the file and the key."""
    path = Path(path)
    data = _read_toml(path)
    garments = data.pop("garments", None)
    if not isinstance(garments, dict) or not garments:
        raise FabricError(f'{path}: needs a table [garments] naming each garment\'s fabric (jeans = "denim")')
    known = load_fabrics()
    for name, table in data.items():
        if not isinstance(table, dict):
            raise FabricError(f"{path}: {name!r} must be a table [{name}] of fabric keys, or a garment under "
                              f"[garments]")
        known[name] = fabric_from_table(name, table, str(path))
    out = {}
    for garment, name in garments.items():
        if not isinstance(name, str) or name not in known:
            raise FabricError(f"{path}: [garments].{garment}: no fabric {name!r}; available: {sorted(known)}")
        out[garment] = known[name]
    return out

