"""Configuration files: YAML presets with ``inherit_from``, dotted overrides, range validation.

A configuration is named either by a packaged preset (``neb_slam_core/configs/<name>.yaml``, listed by
:func:`config_names`) or by the path of a YAML file. A file holds a (partial) nested mapping of the
:class:`~neb_slam_core.config.SlamConfig` fields; whatever it leaves out keeps its default::

    # my_tum.yaml
    inherit_from: tum          # a preset name, or a path relative to this file (../common.yaml)
    tracking:
      lr: 2.0e-2               # every other tracking value stays as tum.yaml (and base.yaml) say

The parent is loaded first (recursively) and the child's mapping is merged over it key by key, so a
section the child mentions keeps the parent's other values. Overrides (``["tracking.lr=0.02"]``, values
read as YAML scalars) are applied last. The result is type-checked and range-checked (:func:`validate`);
every error is a :class:`~neb_slam_core.errors.ConfigError` naming the file (or override) and the dotted
key::

    cfg = load_config("tum", ["mapping.iterations=30"])
    dump_config(cfg, run_dir / "config.yaml")      # fully resolved; load_config(that path) == cfg

Floats may be written ``1e-3`` (YAML 1.2 style) as well as ``1.0e-3``; plain PyYAML reads the former
as a string, so the packaged presets use the latter.
"""

from __future__ import annotations

import copy
import dataclasses
import importlib.resources
import math
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from .config import SlamConfig, config_from_dict, config_to_dict, is_delta_step, key_source
from .errors import ConfigError

#: the key of a YAML file that names its parent
INHERIT_KEY = "inherit_from"
#: packaged presets: ``<package>/configs/<name>.yaml``
PRESET_PACKAGE = "neb_slam_core"
PRESET_FOLDER = "configs"
#: hash-grid backends (the same tuple as ``scene.hash_grid.BACKENDS``; kept here so that loading a
#: configuration does not import torch; a test checks that the two agree)
GRID_BACKENDS = ("auto", "fast", "reference")
TRACKING_METHODS = ("adam", "gauss_newton")
MOTION_MODELS = ("frames", "stamps")
PREDICTIONS = ("motion", "features")
ALLOC_CENTRES = ("mean", "cover")

_PRESET_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_-]*")
_DOTTED_KEY = re.compile(r"[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*")
_DEVICE = re.compile(r"cpu|cuda(?::\d+)?")


# ----------------------------------------------------------------------------------------------- YAML


class _YamlLoader(yaml.SafeLoader):
    """PyYAML's safe loader, plus: ``1e-3`` is a float (YAML 1.2; YAML 1.1 wants ``1.0e-3``), and a key
    repeated within one mapping is an error (PyYAML silently keeps the last one)."""

    def construct_mapping(self, node, deep=False):
        seen: set[str] = set()
        for key_node, _ in node.value:
            if isinstance(key_node, yaml.ScalarNode) and key_node.value != "<<":
                if key_node.value in seen:
                    raise yaml.constructor.ConstructorError(
                        "while reading a mapping",
                        node.start_mark,
                        f"found the key {key_node.value!r} twice",
                        key_node.start_mark,
                    )
                seen.add(key_node.value)
        return super().construct_mapping(node, deep=deep)


# Floats with an exponent but no dot, or with an unsigned exponent, which the YAML 1.1 resolver leaves as
# strings; tried after PyYAML's own int and float patterns.
_YamlLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."),
)


def _parse_yaml(text: str, label: str) -> Any:
    loader = _YamlLoader(text)
    loader.name = label  # marks in PyYAML's messages then name the file
    try:
        return loader.get_single_data()
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        context = getattr(exc, "context", None)
        raise ConfigError(f"{label}: invalid YAML: {where}{problem}{' (' + context + ')' if context else ''}") from None
    finally:
        loader.dispose()


# -------------------------------------------------------------------------------------------- sources


@dataclass(frozen=True)
class _Source:
    """One configuration file: how messages name it, what identifies it (for cycles), where its relative
    ``inherit_from`` paths start, and the file itself (a Path, or a packaged resource)."""

    label: str
    identity: str
    folder: Any  # Path | importlib.resources.abc.Traversable
    file: Any


def _preset_folder():
    return importlib.resources.files(PRESET_PACKAGE).joinpath(PRESET_FOLDER)


def config_names() -> list[str]:
    """Names of the packaged presets (``base``, ``tum``, ...), sorted."""
    return sorted(
        entry.name[: -len(".yaml")]
        for entry in _preset_folder().iterdir()
        if entry.name.endswith(".yaml") and entry.is_file()
    )


def _is_preset_name(ref: str | Path) -> bool:
    """A bare word (no folder, no ``.yaml``) names a preset; anything else is a path."""
    return isinstance(ref, str) and _PRESET_NAME.fullmatch(ref) is not None


def _resolve(ref: str | Path, including: _Source | None) -> _Source:
    """The source ``ref`` names, from the top level (``including`` None) or from ``including``'s
    ``inherit_from``."""
    context = f"{including.label}: {INHERIT_KEY}: " if including is not None else ""
    if not isinstance(ref, (str, Path)):
        raise ConfigError(f"{context}expected a preset name or a YAML file path, got {ref!r}")
    if _is_preset_name(ref):
        file = _preset_folder().joinpath(f"{ref}.yaml")
        if not file.is_file():
            raise ConfigError(
                f"{context}unknown configuration preset {ref!r}; presets: "
                f"{', '.join(config_names())} (a file path must end in .yaml or name a folder, "
                f"e.g. ./{ref}.yaml)"
            )
        return _Source(f"{PRESET_PACKAGE}/{PRESET_FOLDER}/{ref}.yaml", f"preset:{ref}", _preset_folder(), file)
    if including is not None and including.identity.startswith("preset"):
        # a relative path inside a packaged preset stays inside the packaged folder
        rel = Path(os.path.normpath(str(ref))).as_posix()
        if Path(rel).is_absolute() or rel.startswith(".."):
            raise ConfigError(f"{context}{ref!r}: a packaged preset may only inherit from another preset")
        file = including.folder.joinpath(*rel.split("/"))
        return _Source(f"{PRESET_PACKAGE}/{PRESET_FOLDER}/{rel}", f"preset-file:{rel}", including.folder, file)
    path = Path(ref).expanduser()
    if including is not None and not path.is_absolute():
        path = including.folder / path
    label = os.path.normpath(path)  # for messages only: with symlinks, a/b/../c need not be a/c
    if not path.is_file():
        problem = "is a folder, expected a YAML file" if path.is_dir() else "no such configuration file"
        if not path.exists() and path.stem in config_names():
            problem += f" (for the packaged preset, write just {path.stem!r})"
        raise ConfigError(f"{context}{label}: {problem}")
    return _Source(label, f"file:{path.resolve()}", path.parent, path)


def _read_mapping(source: _Source) -> dict:
    try:
        text = source.file.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{source.label}: cannot read: {exc}") from None
    data = _parse_yaml(text, source.label)
    if data is None:  # an empty file (or only comments)
        return {}
    if not isinstance(data, dict):
        raise ConfigError(
            f"{source.label}: expected a mapping of parameters at the top level, got {type(data).__name__}"
        )
    return data


def _record(sources: dict[str, str], prefix: str, value: Any, label: str) -> None:
    """Note ``label`` as the origin of dotted key ``prefix`` and of every key below it."""
    sources[prefix] = label
    if isinstance(value, dict):
        for k, v in value.items():
            _record(sources, f"{prefix}.{k}", v, label)


def _merge(dst: dict, src: dict, label: str, sources: dict[str, str], prefix: str = "") -> None:
    """Merge ``src`` over ``dst`` in place: mappings key by key (recursively), anything else replaced."""
    for key, value in src.items():
        dotted = f"{prefix}{key}"
        if isinstance(value, dict) and isinstance(dst.get(key), dict):
            sources[dotted] = label
            _merge(dst[key], value, label, sources, dotted + ".")
        else:
            dst[key] = copy.deepcopy(value)
            _record(sources, dotted, value, label)


def _load_tree(source: _Source, chain: tuple[_Source, ...]) -> tuple[dict, dict[str, str]]:
    """``source`` merged over its ancestors, and where each dotted key was set."""
    identities = [s.identity for s in chain]
    if source.identity in identities:
        loop = chain[identities.index(source.identity) :] + (source,)
        raise ConfigError(f"{INHERIT_KEY} cycle: {' -> '.join(s.label for s in loop)}")
    data = _read_mapping(source)
    parent_ref = data.pop(INHERIT_KEY, None)
    if parent_ref is None:
        merged: dict = {}
        sources: dict[str, str] = {}
    else:
        if not isinstance(parent_ref, str) or not parent_ref.strip():
            raise ConfigError(
                f"{source.label}: {INHERIT_KEY}: expected a preset name or a path to a YAML file "
                f"relative to this file, got {parent_ref!r}"
            )
        merged, sources = _load_tree(_resolve(parent_ref.strip(), source), chain + (source,))
    _merge(merged, data, source.label, sources)
    return merged, sources


def _parse_overrides(overrides: list[str] | dict | None) -> list[tuple[str, Any, str]]:
    """``(dotted key, value, label)`` of each override."""
    if overrides is None:
        return []
    items: list[tuple[str, Any, str]] = []
    if isinstance(overrides, Mapping):
        for key, value in overrides.items():
            items.append((str(key), value, f"override {key}"))
    elif isinstance(overrides, (list, tuple)):
        for text in overrides:
            label = f"override {text!r}"
            if not isinstance(text, str) or "=" not in text:
                raise ConfigError(f"{label}: expected 'dotted.key=value', e.g. 'tracking.lr=0.01'")
            key, _, value_text = text.partition("=")
            if not value_text.strip():
                raise ConfigError(f"{label}: missing value after '='")
            items.append((key.strip(), _parse_yaml(value_text, label), label))
    else:
        raise ConfigError(
            f"overrides: expected a list of 'dotted.key=value' strings or a mapping, got {type(overrides).__name__}"
        )
    for key, _, label in items:
        if not _DOTTED_KEY.fullmatch(key):
            raise ConfigError(f"{label}: {key!r} is not a dotted parameter name such as 'tracking.lr'")
    return items


def load_config(name_or_path: str | Path, overrides: list[str] | dict | None = None) -> SlamConfig:
    """The validated configuration named by ``name_or_path`` with ``overrides`` applied.

    Args:
        name_or_path: a packaged preset (a bare word: ``"tum"``) or a YAML file path (anything with a
            folder or a ``.yaml``/``.yml`` suffix, or a :class:`~pathlib.Path`).
        overrides: ``["tracking.lr=0.01", ...]`` (values parsed as YAML) or ``{"tracking.lr": 0.01}``;
            applied after the file and its ``inherit_from`` chain.
    Raises:
        ConfigError: missing file or preset, invalid YAML, an ``inherit_from`` cycle, an unknown key, a
            value of the wrong type or out of range; the message names the file (or the override) and
            the dotted key.
    """
    top = _resolve(name_or_path, None)
    merged, sources = _load_tree(top, ())
    for key, value, label in _parse_overrides(overrides):
        nested: Any = value
        for part in reversed(key.split(".")):
            nested = {part: nested}
        _merge(merged, nested, label, sources)
    sources[""] = top.label
    cfg = config_from_dict(SlamConfig, merged, sources=sources)
    _raise_problems(config_problems(cfg), sources)
    return cfg


def config_to_yaml(cfg: SlamConfig) -> str:
    """The fully resolved ``cfg`` as YAML text (every parameter, in declaration order)."""
    return yaml.safe_dump(config_to_dict(cfg), sort_keys=False, default_flow_style=False)


def dump_config(cfg: SlamConfig, path: str | Path) -> None:
    """Write ``cfg`` fully resolved to ``path`` (YAML); ``load_config(path) == cfg``.

    Raises:
        ConfigError: ``cfg`` does not validate (it could not be loaded back), or ``path`` cannot be written.
    """
    validate(cfg)
    text = (
        "# NeB-SLAM configuration, fully resolved (every parameter; no inherit_from).\n"
        "# Load it with neb_slam_core.config_io.load_config(<this file>).\n" + config_to_yaml(cfg)
    )
    try:
        Path(path).write_text(text, encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot write the configuration: {exc.strerror or exc}") from None


# ----------------------------------------------------------------------------------------- validation


@dataclass(frozen=True)
class ConfigProblem:
    """One out-of-range value: its dotted ``key``, the ``value`` found and what was ``expected``."""

    key: str
    value: Any
    expected: str


@dataclass(frozen=True)
class _Int:
    lo: int
    hi: int | None = None

    def ok(self, v: Any) -> bool:
        return isinstance(v, int) and not isinstance(v, bool) and v >= self.lo and (self.hi is None or v <= self.hi)

    def expected(self) -> str:
        return f"an integer >= {self.lo}" if self.hi is None else f"an integer in {self.lo}..{self.hi}"


@dataclass(frozen=True)
class _Num:
    """A finite number in an interval; ``None`` bounds are open-ended."""

    lo: float | None
    hi: float | None = None
    lo_open: bool = True
    hi_open: bool = False

    def ok(self, v: Any) -> bool:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            return False
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return False
        return self.hi is None or (v < self.hi if self.hi_open else v <= self.hi)

    def expected(self) -> str:
        if self.hi is None:
            return f"a finite number {'>' if self.lo_open else '>='} {self.lo:g}"
        return f"a number in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"


@dataclass(frozen=True)
class _Choice:
    choices: tuple[str, ...]

    def ok(self, v: Any) -> bool:
        return isinstance(v, str) and v in self.choices

    def expected(self) -> str:
        return "one of " + ", ".join(self.choices)


@dataclass(frozen=True)
class _Pattern:
    pattern: re.Pattern
    text: str

    def ok(self, v: Any) -> bool:
        return isinstance(v, str) and self.pattern.fullmatch(v) is not None

    def expected(self) -> str:
        return self.text


@dataclass(frozen=True)
class _Bool:
    def ok(self, v: Any) -> bool:
        return isinstance(v, bool)

    def expected(self) -> str:
        return "true or false"


@dataclass(frozen=True)
class _DeltaStep:
    def ok(self, v: Any) -> bool:
        return is_delta_step(v)

    def expected(self) -> str:
        return "0 or a power of two at most 1 (0.0009765625 is 2^-10)"


_POSITIVE = _Num(0.0)
_NON_NEGATIVE = _Num(0.0, lo_open=False)
_POSITIVE_INT = _Int(1)
_COUNT = _Int(0)

#: the range of every parameter (a test checks that each field of SlamConfig has an entry here)
RULES: dict[str, Any] = {
    "block.edge_m": _POSITIVE,
    "block.grid.n_levels": _POSITIVE_INT,
    "block.grid.n_features_per_level": _POSITIVE_INT,
    "block.grid.log2_hashmap_size": _Int(10, 24),
    "block.grid.base_resolution": _POSITIVE_INT,
    "block.grid.max_resolution": _POSITIVE_INT,
    "block.grid.init_scale": _NON_NEGATIVE,
    "block.alloc_threshold": _Num(0.0, 1.0, lo_open=True, hi_open=True),
    "block.alloc_n_points": _POSITIVE_INT,
    "block.alloc_centre": _Choice(ALLOC_CENTRES),
    "block.blend_m": _NON_NEGATIVE,
    "block.observed_voxel_m": _NON_NEGATIVE,
    "one_blob.n_bins": _Int(2),
    "one_blob.period_m": _POSITIVE,
    "decoder.hidden_dim": _POSITIVE_INT,
    "decoder.feature_dim": _POSITIVE_INT,
    "render.truncation_m": _POSITIVE,
    "render.sampling.n_uniform": _POSITIVE_INT,
    "render.sampling.n_surface": _COUNT,
    "render.sampling.near_m": _NON_NEGATIVE,
    "render.sampling.far_m": _POSITIVE,
    "render.sampling.surface_range_m": _POSITIVE,
    "render.sampling.skip_behind_m": _NON_NEGATIVE,
    "render.weights.colour": _NON_NEGATIVE,
    "render.weights.depth": _NON_NEGATIVE,
    "render.weights.sdf": _NON_NEGATIVE,
    "render.weights.free_space": _NON_NEGATIVE,
    "render.weights.smoothness": _NON_NEGATIVE,
    "render.smoothness_points": _COUNT,
    "render.smoothness_step_m": _POSITIVE,
    "render.depth_noise_weights": _Bool(),
    "tracking.n_rays": _POSITIVE_INT,
    "tracking.iterations": _POSITIVE_INT,
    "tracking.lr": _POSITIVE,
    "tracking.border_px": _COUNT,
    "tracking.failure_ratio": _Num(1.0),
    "tracking.failure_min_residual_m": _NON_NEGATIVE,
    "tracking.min_valid_rays": _COUNT,
    "tracking.method": _Choice(TRACKING_METHODS),
    "tracking.gn_damping": _NON_NEGATIVE,
    "tracking.gn_stop_step_m": _NON_NEGATIVE,
    "tracking.motion_model": _Choice(MOTION_MODELS),
    "tracking.max_extrapolation": _NON_NEGATIVE,
    "tracking.prediction": _Choice(PREDICTIONS),
    "tracking.coarse_rays": _COUNT,
    "tracking.coarse_stop_step_m": _NON_NEGATIVE,
    "tracking.relocalise": _Bool(),
    "tracking.observed_only": _Bool(),
    "tracking.colour_timing": _Bool(),
    "tracking.colour_scale": _NON_NEGATIVE,
    "tracking.motion_prior_m_s2": _NON_NEGATIVE,
    "tracking.motion_prior_rad_s2": _NON_NEGATIVE,
    "keyframes.every": _POSITIVE_INT,
    "keyframes.every_s": _NON_NEGATIVE,
    "keyframes.pixel_fraction": _Num(0.0, 1.0, lo_open=True, hi_open=False),
    "mapping.every": _POSITIVE_INT,
    "mapping.iterations": _POSITIVE_INT,
    "mapping.first_iterations": _POSITIVE_INT,
    "mapping.n_rays": _POSITIVE_INT,
    "mapping.n_rays_newest_block": _COUNT,
    "mapping.grid_lr": _POSITIVE,
    "mapping.decoder_lr": _POSITIVE,
    "mapping.pose_lr": _POSITIVE,
    "mapping.optimise_poses": _Bool(),
    "mesh.voxel_size_m": _POSITIVE,
    "mesh.cull_distance_m": _POSITIVE,
    "mesh.batch_points": _POSITIVE_INT,
    "grid_backend": _Choice(GRID_BACKENDS),
    "device": _Pattern(_DEVICE, "cpu, cuda or cuda:N"),
    "seed": _COUNT,
    "loop.enabled": _Bool(),
    "loop.vocabulary": _Pattern(re.compile(r"[^\x00]*"), "'' (the shipped vocabulary) or a file path"),
    "loop.n_features": _Int(10),
    "loop.orb_scale_factor": _Num(1.0, 2.0, lo_open=True, hi_open=False),
    "loop.orb_levels": _Int(1, 16),
    "loop.fast_threshold": _Int(1, 255),
    "loop.min_image_width_px": _COUNT,
    "loop.top_k": _POSITIVE_INT,
    "loop.temporal_window": _COUNT,
    "loop.neighbours": _POSITIVE_INT,
    "loop.n_loop_keyframes": _Int(1, 2),
    "loop.match_ratio": _Num(0.0, 1.0, lo_open=True, hi_open=False),
    "loop.max_match_distance": _Int(0, 256),
    "loop.ransac_iterations": _POSITIVE_INT,
    "loop.reprojection_error_px": _POSITIVE,
    "loop.max_point_error_m": _POSITIVE,
    "loop.min_inliers": _Int(4),
    "loop.min_inlier_ratio": _Num(0.0, 1.0, lo_open=False, hi_open=False),
    "loop.correction_pixels": _Int(10),
    "loop.depth_stride": _Int(1, 16),
    "loop.max_fit_rms_px": _POSITIVE,
    "loop.min_valid_share": _Num(0.0, 1.0, lo_open=False, hi_open=False),
    "loop.min_correction_cm": _Num(0.0, lo_open=False),
    "loop.min_correction_deg": _Num(0.0, lo_open=False),
    "loop.register_neighbours": _COUNT,
    "loop.map_iterations": _COUNT,
    "loop.joint_iterations": _COUNT,
    "live.first_iterations": _POSITIVE_INT,
    "live.chunk_iterations": _POSITIVE_INT,
    "live.torch_threads": _COUNT,
    "live.max_gap_s": _NON_NEGATIVE,
    "live.max_turn_deg": _NON_NEGATIVE,
    "live.max_gap_growth": _NON_NEGATIVE,
    "live.background_nice": _Int(0, 19),
    "live.mapping_process": _Bool(),
    "live.update_tolerance": _NON_NEGATIVE,
    "live.update_float16": _Bool(),
    "live.update_delta_step": _DeltaStep(),
}


def _get(cfg: Any, key: str) -> Any:
    for part in key.split("."):
        cfg = getattr(cfg, part)
    return cfg


def leaf_keys(cls: type = SlamConfig, prefix: str = "") -> list[str]:
    """Dotted names of every parameter of config dataclass ``cls`` (``"tracking.lr"``, ...)."""
    import typing

    hints = typing.get_type_hints(cls)
    keys = []
    for f in dataclasses.fields(cls):
        if dataclasses.is_dataclass(hints[f.name]):
            keys += leaf_keys(hints[f.name], f"{prefix}{f.name}.")
        else:
            keys.append(prefix + f.name)
    return keys


def config_problems(cfg: SlamConfig) -> list[ConfigProblem]:
    """Every value of ``cfg`` outside its range (:data:`RULES`) or inconsistent with another; empty when
    ``cfg`` is valid."""
    problems: list[ConfigProblem] = []
    bad: set[str] = set()
    for key, rule in RULES.items():
        try:
            value = _get(cfg, key)
        except AttributeError:
            continue  # a parameter that this version of SlamConfig does not have
        if not rule.ok(value):
            problems.append(ConfigProblem(key, value, rule.expected()))
            bad.add(key)

    def need(key: str, others: tuple[str, ...], ok, expected: str) -> None:
        if bad.isdisjoint((key,) + others) and not ok():
            problems.append(ConfigProblem(key, _get(cfg, key), expected))

    b, s = cfg.block, cfg.render.sampling
    need(
        "block.grid.max_resolution",
        ("block.grid.base_resolution",),
        lambda: b.grid.max_resolution >= b.grid.base_resolution,
        f">= block.grid.base_resolution ({b.grid.base_resolution})",
    )
    need(
        "block.blend_m",
        ("block.edge_m",),
        lambda: b.blend_m <= b.edge_m / 2,
        f"<= half of block.edge_m ({b.edge_m / 2:g})",
    )
    need(
        "block.observed_voxel_m",
        ("block.edge_m",),
        lambda: b.observed_voxel_m == 0 or b.edge_m / 256 <= b.observed_voxel_m <= b.edge_m,
        f"0 or between block.edge_m / 256 ({b.edge_m / 256:g}: at most 256^3 voxels a block) and block.edge_m",
    )
    need(
        "one_blob.period_m",
        ("block.edge_m",),
        lambda: cfg.one_blob.period_m > b.edge_m,
        f"> block.edge_m ({b.edge_m:g}): a block must not see the one-blob code repeat",
    )
    need(
        "render.sampling.far_m",
        ("render.sampling.near_m",),
        lambda: s.far_m > s.near_m,
        f"> render.sampling.near_m ({s.near_m:g})",
    )
    need(
        "render.sampling.skip_behind_m",
        ("render.truncation_m",),
        lambda: s.skip_behind_m == 0 or s.skip_behind_m >= cfg.render.truncation_m,
        f"0 (off) or >= render.truncation_m ({cfg.render.truncation_m:g}): the SDF loss needs the samples "
        f"up to the truncation distance behind the measured depth",
    )
    need(
        "render.smoothness_step_m",
        ("block.edge_m",),
        lambda: cfg.render.smoothness_step_m < b.edge_m,
        f"< block.edge_m ({b.edge_m:g})",
    )
    need(
        "mesh.voxel_size_m",
        ("block.edge_m",),
        lambda: cfg.mesh.voxel_size_m < b.edge_m,
        f"< block.edge_m ({b.edge_m:g})",
    )
    need(
        "tracking.min_valid_rays",
        ("tracking.n_rays",),
        lambda: cfg.tracking.min_valid_rays <= cfg.tracking.n_rays,
        f"<= tracking.n_rays ({cfg.tracking.n_rays}), or every frame would fail tracking",
    )
    need(
        "loop.neighbours",
        ("loop.temporal_window",),
        lambda: cfg.loop.neighbours <= cfg.loop.temporal_window,
        f"<= loop.temporal_window ({cfg.loop.temporal_window}): "
        "the neighbours that set the threshold are adjacent keyframes",
    )
    if cfg.grid_backend == "fast" and "block.grid.n_features_per_level" not in bad:
        from .scene.hash_grid import FAST_FEATURE_COUNTS  # imports torch: only when it matters

        need(
            "block.grid.n_features_per_level",
            (),
            lambda: b.grid.n_features_per_level in FAST_FEATURE_COUNTS,
            f"one of {', '.join(map(str, FAST_FEATURE_COUNTS))} with grid_backend 'fast'",
        )
    return problems


def _raise_problems(problems: list[ConfigProblem], sources: dict[str, str] | None) -> None:
    if not problems:
        return
    lines = []
    for p in problems:
        where = key_source(sources, p.key)
        lines.append(f"{where + ': ' if where else ''}{p.key} = {p.value!r}: expected {p.expected}")
    if len(lines) == 1:
        raise ConfigError(lines[0])
    raise ConfigError(f"{len(lines)} invalid configuration values:\n  " + "\n  ".join(lines))


def validate(cfg: SlamConfig) -> None:
    """Check that every value of ``cfg`` is in range (positive counts and learning rates, 0 <
    alloc_threshold < 1, near < far, 0 < pixel_fraction <= 1, log2_hashmap_size in 10..24, ...).

    Raises:
        ConfigError: naming the dotted key, the value and what was expected (all problems at once).
    """
    if not isinstance(cfg, SlamConfig):
        raise ConfigError(f"validate: expected a SlamConfig, got {type(cfg).__name__}")
    _raise_problems(config_problems(cfg), None)
