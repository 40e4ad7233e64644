"""`ns-train edygs --help` fits a few screens (issue 17), and what it hides is only what may be hidden.

The help is built in-process by the same ``tyro.cli`` call as ``ns-train`` (nerfstudio's
``AnnotatedBaseConfigUnion``), at one terminal width for both methods compared.
"""

from __future__ import annotations

import dataclasses
import re
import typing
from pathlib import Path
from typing import List

import pytest
import tyro
import yaml

ROOT = Path(__file__).resolve().parents[1]
#: Terminal width of the comparison (the line counts depend on it).
COLUMNS = "100"
#: Where ns-train flags are written down for people and machines to pass.
FLAG_SOURCES = ("README.md", "docs/*.md", "benchmarks/*.py", "scripts/*.sh", "tests/*.py", "edygs_ns/**/*.py")
FLAG = re.compile(r"--pipeline\.[a-z0-9._-]*[a-z0-9](?![a-z0-9._*-])")  # not a pattern like lambda-*


def _help(method: str, monkeypatch, capsys) -> str:
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    monkeypatch.setenv("COLUMNS", COLUMNS)
    capsys.readouterr()
    with pytest.raises(SystemExit):
        tyro.cli(AnnotatedBaseConfigUnion, args=[method, "--help"])
    return capsys.readouterr().out


def _documented_flags() -> List[str]:
    """Every --pipeline.* flag written in the repository (docs, benchmarks, scripts, tests, code)."""
    flags = set()
    for pattern in FLAG_SOURCES:
        for path in ROOT.glob(pattern):
            flags.update(FLAG.findall(path.read_text(encoding="utf-8")))
    return sorted(flags)


def test_edygs_help_is_no_longer_than_splatfactos(monkeypatch, capsys):
    ours = len(_help("edygs", monkeypatch, capsys).splitlines())
    splatfacto = len(_help("splatfacto", monkeypatch, capsys).splitlines())
    assert ours <= splatfacto, f"ns-train edygs --help: {ours} lines, splatfacto's {splatfacto}"


def test_every_flag_the_repository_passes_is_still_on_the_command_line(monkeypatch, capsys):
    flags = _documented_flags()
    assert "--pipeline.model.seeding.grow-mads" in flags and len(flags) > 20  # the scan finds them
    text = _help("edygs", monkeypatch, capsys)
    shown = set(re.findall(r"--pipeline\.[a-z0-9._-]+", text))
    missing = [flag for flag in flags if flag not in shown]
    assert not missing, f"hidden from ns-train but passed in the repository: {missing}"


def test_config_round_trips_through_config_yml():
    from edygs_ns.configs.method_configs import edygs_cpu_method, edygs_method

    for spec in (edygs_method, edygs_cpu_method):
        loaded = yaml.load(yaml.dump(spec.config), Loader=yaml.Loader)  # as eval_setup reads config.yml
        assert loaded == spec.config


def _suppressed_overrides(cls: type) -> List[str]:
    """Names of the fields ``cls`` itself declares with tyro.conf.Suppress (nerfstudio's among them)."""
    marker = typing.get_args(tyro.conf.Suppress[int])[1:]
    hints = typing.get_type_hints(cls, include_extras=True)
    own = cls.__dict__.get("__annotations__", {})
    return [n for n in own if typing.get_origin(hints[n]) is typing.Annotated and hints[n].__metadata__ == marker]


def _default(cls: type, name: str):
    f = next(f for f in dataclasses.fields(cls) if f.name == name)
    return f.default_factory() if f.default is dataclasses.MISSING else f.default


def test_hidden_overrides_of_nerfstudio_fields_keep_nerfstudio_defaults():
    from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanagerConfig
    from nerfstudio.engine.optimizers import AdamOptimizerConfig
    from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
    from nerfstudio.models.base_model import ModelConfig

    from edygs_ns.configs.method_configs import AdamConfig, DecayConfig
    from edygs_ns.data.datamanager import EdygsDataManagerConfig
    from edygs_ns.model.edygs_model import EdygsModelConfig

    #: hidden on purpose with a value of ours
    ours = {(AdamConfig, "eps"): 1e-15}
    pairs = ((EdygsModelConfig, ModelConfig), (EdygsDataManagerConfig, FullImageDatamanagerConfig),
             (AdamConfig, AdamOptimizerConfig), (DecayConfig, ExponentialDecaySchedulerConfig))  # fmt: skip
    for cls, base in pairs:
        base_fields = {f.name for f in dataclasses.fields(base)}
        hidden = [name for name in _suppressed_overrides(cls) if name in base_fields]
        assert hidden, cls
        for name in hidden:
            expected = ours.get((cls, name), _default(base, name))
            assert _default(cls, name) == expected, f"{cls.__name__}.{name}"
