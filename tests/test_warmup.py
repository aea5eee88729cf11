"""The install-time warm-up compiles every numba kernel through the commands a run uses."""

from __future__ import annotations

from pathlib import Path

import pytest

from btmission import warmup


def test_the_warm_up_steps_name_real_files_and_commands(tmp_path: Path) -> None:
    from btmission.cli.main import cli

    steps = warmup._commands(tmp_path)
    names = [name for name, _ in steps]
    assert names == [
        "D*+ planner",
        "GA dispatch",
        "simulator LiDAR",
        "simulator depth camera",
        "relocalization ray casting",
    ]
    for _, args in steps:
        group: object = cli
        for word in args:  # each step's command path exists (bench planner, dispatch static ...)
            commands = getattr(group, "commands", None)
            if commands is None or word not in commands:
                break
            group = commands[word]
        assert not hasattr(group, "commands"), args
        for arg in args:
            if arg.endswith(".yaml"):
                assert Path(arg).is_file(), arg


def test_the_warm_up_calls_the_kernels_no_command_runs() -> None:
    assert [name for name, _ in warmup._calls()] == ["viewer surface mesh"]
    for _, call in warmup._calls():
        call()


@pytest.mark.slow
def test_the_warm_up_runs_every_step() -> None:
    lines: list[str] = []
    total = warmup.warm_up(lines.append)
    assert len(lines) == 6 and all(" compiled in " in line for line in lines), lines
    assert total > 0
