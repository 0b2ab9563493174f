"""Atomic writes and the check made before a run that its outputs can be written (``files``)."""

from __future__ import annotations

import os

import pytest

from humanoid_prime.errors import PrimeError
from humanoid_prime.files import atomic_write_text, output_problem


def test_a_write_over_a_folder_names_the_folder_not_a_temporary_file(tmp_path):
    (tmp_path / "cal.yaml").mkdir()
    with pytest.raises(PrimeError) as error:
        atomic_write_text(tmp_path / "cal.yaml", "joints: {}\n")
    assert str(error.value) == f"cannot write {tmp_path / 'cal.yaml'}: it is a folder; give a file name"
    assert [p.name for p in tmp_path.iterdir()] == ["cal.yaml"]


def test_a_write_where_nothing_can_be_created_names_the_file_asked_for():
    with pytest.raises(PrimeError) as error:
        atomic_write_text("/proc/x.json", "{}\n")
    assert str(error.value) == "cannot write /proc/x.json: No such file or directory"


@pytest.mark.parametrize("path", ["/proc/x.json", "/proc/a/b/x.json"])
def test_an_output_where_the_temporary_file_cannot_be_made_is_a_problem_before_the_run(path):
    # /proc is writable to root by its permission bits; only making the file tells
    problem = output_problem(path)
    assert problem is not None and problem.endswith("in /proc" if os.geteuid() else
                                                     "nothing can be created in /proc (No such file or directory)")


def test_the_check_before_the_run_leaves_nothing_behind(tmp_path):
    assert output_problem(tmp_path / "out.json") is None
    assert output_problem(tmp_path / "new" / "deeper" / "out.json") is None
    assert output_problem(tmp_path / "fold", directory=True) is None
    assert list(tmp_path.iterdir()) == []
