"""Shared fixtures: the built-in libraries, a CLI runner, small library builders."""

from __future__ import annotations

import textwrap

import pytest
from click.testing import CliRunner

from btmission.plugins import load_library
from btmission.spec.library import Library, load_library_text


@pytest.fixture(scope="session")
def aerial() -> Library:
    return load_library("aerial").library


@pytest.fixture(scope="session")
def ground() -> Library:
    return load_library("ground").library


@pytest.fixture()
def runner() -> CliRunner:
    return CliRunner()


def lib_from(body: str, file: str = "lib.yaml"):  # type: ignore[no-untyped-def]
    """Load a library from an indented YAML snippet; returns (library, diagnostics)."""
    return load_library_text(textwrap.dedent(body).lstrip("\n"), file)
