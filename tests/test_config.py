"""Typed dataclass configs: YAML/JSON files, key=value overrides, field docs, clear errors."""

from dataclasses import dataclass, field

import pytest

from n2d_common.config import field_docs, flat_fields, load_config, to_dict
from n2d_common.errors import ConfigError


@dataclass
class Inner:
    samples: int = 8
    """Samples per pixel."""
    denoise: bool = True
    """Run the denoiser."""


@dataclass
class Outer:
    name: str = "box"
    """Object name."""
    scale_m: float = 0.1
    """Edge length in metres."""
    angles_deg: list[float] = field(default_factory=lambda: [0.0, 90.0])
    """Stops."""
    render: Inner = field(default_factory=Inner)
    """Render settings."""

    def __post_init__(self):
        if self.scale_m <= 0:
            raise ValueError("scale_m must be > 0")


def test_file_then_overrides(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("name: bottle\nrender:\n  samples: 16\n")
    cfg = load_config(Outer, path, ["render.denoise=false", "scale_m=0.25", "angles_deg=[0, 45, 90]"])
    assert cfg == Outer("bottle", 0.25, [0.0, 45.0, 90.0], Inner(16, False))
    assert load_config(Outer, None, []) == Outer()
    json_path = tmp_path / "c.json"
    json_path.write_text('{"render": {"samples": 4}}')
    assert load_config(Outer, json_path).render.samples == 4
    assert to_dict(cfg)["render"] == {"samples": 16, "denoise": False}


@pytest.mark.parametrize("text,overrides,match", [
    ("name: [unclosed\n", [], "not valid YAML"),
    ("- a list\n", [], "must hold a mapping"),
    ("colour: red\n", [], "unknown key"),
    ("", ["render.samples=many"], "expected int"),
    ("", ["scale_m=-1"], "scale_m must be > 0"),
    ("", ["render.denoise=maybe"], "true/false"),
    ("", ["novalue"], "key=value"),
])
def test_bad_config_is_one_clear_error(tmp_path, text, overrides, match):
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=match):
        load_config(Outer, path, overrides)


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="cannot read config"):
        load_config(Outer, tmp_path / "nope.yaml")


def test_field_docs_feed_help_and_parameters():
    assert field_docs(Outer)["scale_m"] == "Edge length in metres."
    flat = {name: (default, doc) for name, _, default, doc in flat_fields(Outer)}
    assert flat["render.samples"] == (8, "Samples per pixel.")
    assert flat["name"] == ("box", "Object name.")
