"""Shared test helpers: the paper's spec, spec mutation, and CLI runs through main(argv)."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import yaml

from fabkit.cli import main

ROOT = Path(__file__).resolve().parents[1]
SPECS = ROOT / "specs"
PAPER = SPECS / "surface.yaml"


def paper_raw() -> dict:
    return yaml.safe_load(PAPER.read_text())


def write_spec(tmp_path: Path, raw: dict, name: str = "spec.yaml") -> Path:
    p = tmp_path / name
    p.write_text(yaml.safe_dump(raw, sort_keys=False))
    return p


def mutated(changes: dict, drop: tuple[str, ...] = ()) -> dict:
    """The paper's spec with dotted keys set (or dropped)."""
    raw = copy.deepcopy(paper_raw())
    for key, value in changes.items():
        node = raw
        parts = key.split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = value
    for key in drop:
        node = raw
        parts = key.split(".")
        for p in parts[:-1]:
            node = node[p]
        del node[parts[-1]]
    return raw


@pytest.fixture
def cli(capsys, monkeypatch, tmp_path):
    """Run ``fabkit ARGS`` in-process from a scratch folder; returns (code, stdout, stderr)."""
    monkeypatch.chdir(tmp_path)

    def run(*argv):
        code = main([str(a) for a in argv])
        out, err = capsys.readouterr()
        return code, out, err

    return run
