"""Configuration files: presets, inherit_from, overrides, validation, dump/load round trip."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from neb_slam_core.config import (
    BlockConfig,
    HashGridConfig,
    KeyframeConfig,
    MappingConfig,
    RenderConfig,
    SamplingConfig,
    SlamConfig,
    TrackingConfig,
    config_from_dict,
)
from neb_slam_core.config_io import (
    GRID_BACKENDS,
    RULES,
    config_names,
    config_problems,
    config_to_yaml,
    dump_config,
    leaf_keys,
    load_config,
    validate,
)
from neb_slam_core.errors import ConfigError

PRESETS = ("base", "tum", "scannet", "replica", "synthetic", "small", "ci")
BASE = SlamConfig()


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def with_sampling(cfg: SlamConfig, **changes) -> SlamConfig:
    return replace(cfg, render=replace(cfg.render, sampling=replace(cfg.render.sampling, **changes)))


# ------------------------------------------------------------------------------------------- presets


def test_the_packaged_presets_are_listed():
    assert set(PRESETS) <= set(config_names())
    assert config_names() == sorted(config_names())


@pytest.mark.parametrize("name", PRESETS)
def test_every_preset_loads_and_validates(name):
    cfg = load_config(name)
    assert isinstance(cfg, SlamConfig)
    validate(cfg)
    assert config_problems(cfg) == []


def test_base_yaml_is_exactly_the_dataclass_defaults():
    # so that base.yaml (the file users read) and config.py can never drift apart
    assert load_config("base") == BASE


def test_tum_preset_has_the_papers_tum_values_and_ours_for_the_kinect():
    expected = replace(
        BASE,
        # ours: each ray's geometry weighed by its depth's noise
        render=replace(
            BASE.render,
            truncation_m=0.05,
            sampling=replace(BASE.render.sampling, far_m=5.0),
            depth_noise_weights=True,
        ),
        # the paper's learning rate; ours: 2048 pixels, colour at the depth image's time, weighing 1 in
        # tracking, poses fused with the constant-velocity prediction
        tracking=replace(
            BASE.tracking, lr=1e-2, n_rays=2048, colour_timing=True, colour_scale=0.2, motion_prior_m_s2=1.5
        ),
        mapping=replace(BASE.mapping, iterations=20),
        # ours: loop fits within 1 px, loop keyframes' depth at 160x120
        loop=replace(BASE.loop, max_fit_rms_px=1.0, depth_stride=4),
    )
    assert load_config("tum") == expected


def test_scannet_preset_samples_96_plus_21():
    assert load_config("scannet") == with_sampling(BASE, n_uniform=96, n_surface=21, far_m=8.0)


def test_replica_and_small_presets():
    assert load_config("replica") == BASE
    small = load_config("small")
    assert small == replace(BASE, block=replace(BASE.block, grid=replace(BASE.block.grid, log2_hashmap_size=14)))
    assert small.block.grid.table_size == 2**14


def test_synthetic_and_ci_presets():
    synthetic = load_config("synthetic")
    assert synthetic == replace(with_sampling(BASE, far_m=8.0), tracking=replace(BASE.tracking, lr=1e-2))
    ci = load_config("ci")
    # inherits synthetic's far plane and tracking, spends a smaller mapping budget
    assert ci.render == synthetic.render and ci.tracking == synthetic.tracking
    assert ci.block == BASE.block and ci.decoder == BASE.decoder and ci.keyframes == BASE.keyframes
    assert ci.mapping == replace(BASE.mapping, iterations=8, n_rays=1024, n_rays_newest_block=256)


# --------------------------------------------------------------------------------------- inheritance


def test_a_child_that_sets_one_value_keeps_the_parents_others(tmp_path):
    child = write(tmp_path / "child.yaml", "inherit_from: tum\ntracking:\n  lr: 0.5\n")
    tum = load_config("tum")
    assert load_config(child) == replace(tum, tracking=replace(tum.tracking, lr=0.5))


def test_relative_inherit_from_and_a_three_level_chain(tmp_path):
    # runs/child.yaml -> ../common/parent.yaml -> preset small -> preset base
    write(
        tmp_path / "common" / "parent.yaml",
        "inherit_from: small\nmapping:\n  iterations: 7\n  n_rays: 100\ntracking:\n  iterations: 3\n",
    )
    child = write(
        tmp_path / "runs" / "child.yaml", "inherit_from: ../common/parent.yaml\nmapping:\n  n_rays: 200\nseed: 5\n"
    )
    cfg = load_config(str(child))
    small = load_config("small")
    assert cfg == replace(
        small,
        seed=5,
        tracking=replace(small.tracking, iterations=3),
        mapping=replace(small.mapping, iterations=7, n_rays=200),
    )


def test_a_child_may_replace_a_whole_section_value_by_value(tmp_path):
    parent = write(tmp_path / "p.yaml", "render:\n  sampling:\n    n_uniform: 40\n    near_m: 0.3\n")
    child = write(tmp_path / "c.yaml", f"inherit_from: {parent.name}\nrender:\n  sampling:\n    near_m: 0.2\n")
    assert load_config(child) == with_sampling(BASE, n_uniform=40, near_m=0.2)


def test_an_inherit_from_cycle_is_an_error_naming_the_chain(tmp_path):
    write(tmp_path / "a.yaml", "inherit_from: b.yaml\nseed: 1\n")
    write(tmp_path / "b.yaml", "inherit_from: sub/c.yaml\n")
    write(tmp_path / "sub" / "c.yaml", "inherit_from: ../a.yaml\n")
    with pytest.raises(ConfigError, match="cycle") as err:
        load_config(tmp_path / "a.yaml")
    message = str(err.value)
    assert message.count("a.yaml") == 2 and "b.yaml" in message and "c.yaml" in message
    assert message.index("b.yaml") < message.index("c.yaml")
    write(tmp_path / "self.yaml", "inherit_from: self.yaml\n")
    with pytest.raises(ConfigError, match="cycle"):
        load_config(tmp_path / "self.yaml")


def test_a_missing_parent_names_the_including_file(tmp_path):
    child = write(tmp_path / "child.yaml", "inherit_from: nowhere.yaml\n")
    with pytest.raises(ConfigError, match=r"child\.yaml: inherit_from: .*nowhere\.yaml: no such configuration file"):
        load_config(child)
    write(tmp_path / "child2.yaml", "inherit_from: no_such_preset\n")
    with pytest.raises(
        ConfigError, match=r"child2\.yaml: inherit_from: unknown configuration preset 'no_such_preset'.*tum"
    ):
        load_config(tmp_path / "child2.yaml")
    write(tmp_path / "child3.yaml", "inherit_from: [a, b]\n")
    with pytest.raises(ConfigError, match=r"child3\.yaml: inherit_from: expected a preset name"):
        load_config(tmp_path / "child3.yaml")


# ------------------------------------------------------------------------------------------ errors


def test_missing_file_unknown_preset_and_folder(tmp_path):
    with pytest.raises(ConfigError, match=r"missing\.yaml: no such configuration file"):
        load_config(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match=r"unknown configuration preset 'tumm'.*base, ci"):
        load_config("tumm")
    with pytest.raises(ConfigError, match="is a folder"):
        load_config(str(tmp_path) + "/")
    with pytest.raises(
        ConfigError,
        match=r"tum\.yaml: no such configuration file \(for the packaged preset, "
        r"write just 'tum'\)",
    ):
        load_config(tmp_path / "tum.yaml")
    with pytest.raises(ConfigError, match="expected a preset name or a YAML file path, got None"):
        load_config(None)


def test_unknown_key_names_the_file_and_the_dotted_key(tmp_path):
    f = write(tmp_path / "bad.yaml", "inherit_from: tum\ntracking:\n  lrr: 0.1\n")
    with pytest.raises(
        ConfigError,
        match=r"bad\.yaml: tracking\.lrr: unknown parameter of TrackingConfig; "
        r"did you mean 'lr'\?",
    ):
        load_config(f)
    f = write(tmp_path / "bad2.yaml", "tracker:\n  lr: 0.1\n")
    with pytest.raises(ConfigError, match=r"bad2\.yaml: tracker: unknown parameter of SlamConfig"):
        load_config(f)


@pytest.mark.parametrize(
    "text, key, expected",
    [
        ("mapping:\n  iterations: many\n", "mapping.iterations", "expected an integer, got 'many'"),
        ("mapping:\n  iterations: 2.5\n", "mapping.iterations", "expected an integer, got 2.5"),
        ("tracking:\n  lr: '0.1'\n", "tracking.lr", "expected a number, got '0.1'"),
        ("tracking:\n  lr: true\n", "tracking.lr", "expected a number, got True"),
        ("mapping:\n  optimise_poses: 1\n", "mapping.optimise_poses", "expected true or false, got 1"),
        ("device: 0\n", "device", "expected a string, got 0"),
        ("render: 5\n", "render", "expected a mapping of RenderConfig parameters"),
    ],
)
def test_wrong_type_names_the_file_and_the_dotted_key(tmp_path, text, key, expected):
    f = write(tmp_path / "typed.yaml", text)
    with pytest.raises(ConfigError) as err:
        load_config(f)
    assert str(err.value).startswith(f"{f}: {key}: {expected}")


@pytest.mark.parametrize(
    "text, key",
    [
        ("keyframes:\n  pixel_fraction: 1.5\n", "keyframes.pixel_fraction"),
        ("keyframes:\n  pixel_fraction: 0.0\n", "keyframes.pixel_fraction"),
        ("block:\n  alloc_threshold: 1.0\n", "block.alloc_threshold"),
        ("block:\n  grid:\n    log2_hashmap_size: 25\n", "block.grid.log2_hashmap_size"),
        ("block:\n  grid:\n    log2_hashmap_size: 9\n", "block.grid.log2_hashmap_size"),
        ("tracking:\n  lr: 0\n", "tracking.lr"),
        ("tracking:\n  lr: .inf\n", "tracking.lr"),
        ("mapping:\n  grid_lr: .nan\n", "mapping.grid_lr"),
        ("mapping:\n  iterations: 0\n", "mapping.iterations"),
        ("tracking:\n  n_rays: -5\n", "tracking.n_rays"),
        ("render:\n  truncation_m: 0.0\n", "render.truncation_m"),
        ("render:\n  sampling:\n    near_m: 6.0\n", "render.sampling.far_m"),  # near == far
        ("device: gpu\n", "device"),
        ("device: 'cuda:'\n", "device"),
        ("grid_backend: cuda\n", "grid_backend"),
        ("seed: -1\n", "seed"),
        ("one_blob:\n  period_m: 4.0\n", "one_blob.period_m"),  # must exceed the 5 m block edge
        ("tracking:\n  min_valid_rays: 2000\n", "tracking.min_valid_rays"),  # more than n_rays
        ("live:\n  update_delta_step: 0.001\n", "live.update_delta_step"),  # not a power of two
        ("live:\n  update_delta_step: 2.0\n", "live.update_delta_step"),  # above 1
    ],
)
def test_out_of_range_names_the_file_and_the_dotted_key(tmp_path, text, key):
    f = write(tmp_path / "range.yaml", text)
    with pytest.raises(ConfigError) as err:
        load_config(f)
    assert str(err.value).startswith(f"{f}: {key} = ")
    assert "expected" in str(err.value)


def test_range_errors_name_the_file_that_set_the_value(tmp_path):
    parent = write(tmp_path / "parent.yaml", "keyframes:\n  every: 0\n")
    child = write(tmp_path / "child.yaml", "inherit_from: parent.yaml\ntracking:\n  lr: -1.0\n")
    with pytest.raises(ConfigError) as err:
        load_config(child)
    message = str(err.value)
    assert message.startswith("2 invalid configuration values")
    assert f"{parent}: keyframes.every = 0: expected an integer >= 1" in message
    assert f"{child}: tracking.lr = -1.0: expected a finite number > 0" in message


def test_validate_checks_a_config_built_in_code():
    validate(BASE)
    with pytest.raises(ConfigError, match=r"^keyframes\.pixel_fraction = 2\.0: expected a number in \(0, 1\]$"):
        validate(replace(BASE, keyframes=KeyframeConfig(pixel_fraction=2.0)))
    with pytest.raises(ConfigError, match=r"tracking\.iterations = '10': expected an integer >= 1"):
        validate(replace(BASE, tracking=TrackingConfig(iterations="10")))
    with pytest.raises(ConfigError, match="expected a SlamConfig"):
        validate(TrackingConfig())


def test_every_parameter_has_a_range_rule():
    # a new field in config.py needs its range here (and its line in base.yaml)
    assert set(RULES) == set(leaf_keys())


def test_grid_backends_match_the_hash_grid():
    from neb_slam_core.scene.hash_grid import BACKENDS, FAST_FEATURE_COUNTS

    assert GRID_BACKENDS == BACKENDS
    odd = replace(BASE, grid_backend="fast", block=BlockConfig(grid=HashGridConfig(n_features_per_level=3)))
    assert 3 not in FAST_FEATURE_COUNTS
    with pytest.raises(ConfigError, match=r"block\.grid\.n_features_per_level = 3: .*grid_backend 'fast'"):
        validate(odd)
    validate(replace(odd, grid_backend="reference"))


def test_invalid_yaml_and_duplicate_keys_name_file_and_line(tmp_path):
    f = write(tmp_path / "broken.yaml", "tracking:\n  lr: [0.1\n")
    with pytest.raises(ConfigError, match=r"broken\.yaml: invalid YAML: line \d+, column \d+"):
        load_config(f)
    f = write(tmp_path / "twice.yaml", "tracking:\n  lr: 0.1\n  lr: 0.2\n")
    with pytest.raises(ConfigError, match=r"twice\.yaml: invalid YAML: line 3, column 3: found the key 'lr' twice"):
        load_config(f)
    f = write(tmp_path / "list.yaml", "- 1\n- 2\n")
    with pytest.raises(ConfigError, match=r"list\.yaml: expected a mapping of parameters at the top level, got list"):
        load_config(f)


def test_empty_files_and_sections_mean_defaults(tmp_path):
    assert load_config(write(tmp_path / "empty.yaml", "# nothing yet\n")) == BASE
    assert load_config(write(tmp_path / "section.yaml", "tracking:\n  # lr: 0.1\n")) == BASE


def test_exponent_floats_without_a_dot_are_numbers(tmp_path):
    # plain YAML 1.1 reads 1e-3 as a string; users write it that way anyway
    f = write(
        tmp_path / "exp.yaml",
        "tracking:\n  lr: 1e-3\nmapping:\n  grid_lr: 5E-2\n  pose_lr: 1.5e-4\nrender:\n  weights:\n    sdf: 1e3\n",
    )
    cfg = load_config(f)
    assert cfg.tracking.lr == 1e-3 and cfg.mapping.grid_lr == 5e-2 and cfg.mapping.pose_lr == 1.5e-4
    assert cfg.render.weights.sdf == 1000.0 and isinstance(cfg.render.weights.sdf, float)
    # integers stay integers, integers for float fields become floats
    cfg = load_config(write(tmp_path / "ints.yaml", "tracking:\n  n_rays: 100\n  lr: 1\n"))
    assert cfg.tracking.n_rays == 100 and type(cfg.tracking.lr) is float and cfg.tracking.lr == 1.0


# --------------------------------------------------------------------------------------- overrides


def test_overrides_are_applied_last_and_parsed_as_yaml(tmp_path):
    f = write(tmp_path / "f.yaml", "inherit_from: tum\ntracking:\n  lr: 0.5\n")
    cfg = load_config(
        f,
        [
            "tracking.lr=1e-2",
            "mapping.iterations=3",
            "mapping.optimise_poses=false",
            "device=cuda:1",
            "render.sampling.far_m=7",
            " seed = 4 ",
        ],
    )
    tum = load_config("tum")
    assert cfg == replace(
        tum,
        device="cuda:1",
        seed=4,
        tracking=replace(tum.tracking, lr=1e-2),
        mapping=replace(tum.mapping, iterations=3, optimise_poses=False),
        render=replace(tum.render, sampling=replace(tum.render.sampling, far_m=7.0)),
    )


def test_overrides_as_a_mapping():
    cfg = load_config("base", {"tracking.lr": 0.25, "mapping": {"iterations": 3}})
    assert cfg == replace(BASE, tracking=replace(BASE.tracking, lr=0.25), mapping=replace(BASE.mapping, iterations=3))
    assert load_config("base", {}) == load_config("base", []) == load_config("base") == BASE


def test_bad_overrides_name_the_override():
    with pytest.raises(ConfigError, match=r"override 'tracking\.lrr=1': tracking\.lrr: unknown parameter"):
        load_config("tum", ["tracking.lrr=1"])
    with pytest.raises(ConfigError, match=r"override 'tracking\.lr=-1': tracking\.lr = -1\.0: expected"):
        load_config("tum", ["tracking.lr=-1"])
    with pytest.raises(
        ConfigError,
        match=r"override 'mapping\.iterations=lots': mapping\.iterations: "
        r"expected an integer",
    ):
        load_config("tum", ["mapping.iterations=lots"])
    with pytest.raises(ConfigError, match=r"override 'tracking\.lr': expected 'dotted\.key=value'"):
        load_config("tum", ["tracking.lr"])
    with pytest.raises(ConfigError, match=r"override 'tracking\.lr=': missing value"):
        load_config("tum", ["tracking.lr="])
    with pytest.raises(ConfigError, match=r"is not a dotted parameter name"):
        load_config("tum", ["tracking..lr=1"])
    with pytest.raises(ConfigError, match=r"overrides: expected a list"):
        load_config("tum", "tracking.lr=1")


# ---------------------------------------------------------------------------------- dump and load


@pytest.mark.parametrize("name", PRESETS)
def test_dump_then_load_round_trips_every_preset(tmp_path, name):
    cfg = load_config(name)
    dump_config(cfg, tmp_path / "resolved.yaml")
    assert load_config(tmp_path / "resolved.yaml") == cfg


def test_dump_round_trips_awkward_floats_exactly(tmp_path):
    cfg = replace(
        BASE,
        tracking=replace(BASE.tracking, lr=np.float64(1.0) / 3.0, failure_ratio=1e16),
        mapping=MappingConfig(grid_lr=0.1 + 0.2, pose_lr=2.5e-7, optimise_poses=False),
        render=RenderConfig(sampling=SamplingConfig(near_m=0.0, far_m=123456.789)),
        device="cuda:3",
        seed=2**40,
    )
    path = tmp_path / "awkward.yaml"
    dump_config(cfg, path)
    back = load_config(path)
    assert back == cfg
    assert type(back.tracking.lr) is float  # the numpy float went out as a plain float
    text = path.read_text()
    assert text.endswith(config_to_yaml(cfg))
    assert text.startswith("# NeB-SLAM configuration") and "inherit_from" not in text.split("\n", 2)[2]

    # every parameter is written, in declaration order
    def dotted(d, prefix=""):
        for k, v in d.items():
            yield from dotted(v, f"{prefix}{k}.") if isinstance(v, dict) else [prefix + k]

    assert list(dotted(yaml.safe_load(text))) == leaf_keys()


def test_dump_refuses_an_invalid_config_and_names_an_unwritable_path(tmp_path):
    with pytest.raises(ConfigError, match=r"tracking\.lr"):
        dump_config(replace(BASE, tracking=TrackingConfig(lr=-1.0)), tmp_path / "x.yaml")
    assert not (tmp_path / "x.yaml").exists()
    with pytest.raises(ConfigError, match=r"no_dir.*cannot write"):
        dump_config(BASE, tmp_path / "no_dir" / "x.yaml")


def test_config_from_dict_still_builds_sub_configs():
    # the scene persistence code builds sub-configs this way
    block = config_from_dict(BlockConfig, {"edge_m": 4, "grid": {"log2_hashmap_size": 12}}, "block")
    assert block == BlockConfig(edge_m=4.0, grid=HashGridConfig(log2_hashmap_size=12))
    with pytest.raises(ConfigError, match=r"^block\.grid\.size: unknown parameter"):
        config_from_dict(BlockConfig, {"grid": {"size": 12}}, "block")


def test_the_prediction_is_one_of_two():
    assert load_config("live").tracking.prediction == "features"
    assert load_config("tum").tracking.prediction == "motion"
    with pytest.raises(ConfigError, match=r"tracking\.prediction"):
        load_config("tum", ["tracking.prediction=orb"])
    with pytest.raises(ConfigError, match=r"live\.background_nice"):
        load_config("tum", ["live.background_nice=20"])


def test_a_delta_step_is_zero_or_a_power_of_two_at_most_one():
    from neb_slam_core.config import is_delta_step

    assert all(is_delta_step(v) for v in (0, 0.0, 1.0, 0.5, 2.0**-11, 2.0**-30))
    assert not any(is_delta_step(v) for v in (2.0, 0.75, 0.001, -0.5, True, "0.5", float("nan")))
