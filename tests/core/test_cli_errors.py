"""detbench.utils.cli.raised_on_purpose / as_user_error: an error a check of ours raises is the user's (one
line, exit 2); the same exception type from inside numpy or a compiled kernel is a bug and keeps its
traceback."""
import numpy as np
import pytest

from detbench.data.errors import DatasetError
from detbench.utils import cli
from detbench.utils.cli import UserError, as_user_error, is_project_file, raised_on_purpose


def _checked(n):
    if n < 0:
        raise ValueError(
            f"n = {n}: must be >= 0; pass a count")  # a raise statement over two lines
    return n


def _kernel(n):
    return np.zeros(n)  # numpy raises "negative dimensions are not allowed" from C


def _caught(fn, *args) -> BaseException:
    try:
        fn(*args)
    except BaseException as e:  # noqa: BLE001 - the test inspects whatever was raised
        return e
    raise AssertionError("nothing raised")


def test_a_raise_statement_of_ours_is_on_purpose_an_error_from_numpy_is_not():
    assert raised_on_purpose(_caught(_checked, -1))
    assert not raised_on_purpose(_caught(_kernel, -1))
    assert not raised_on_purpose(_caught(int, "x"))  # a builtin's error, no frame of ours raising it


def test_as_user_error_keeps_a_bug_as_it_is():
    ue = as_user_error(_caught(_checked, -1), prefix="--n: ")
    assert isinstance(ue, UserError) and ue.code == 2 and str(ue) == "--n: n = -1: must be >= 0; pass a count"
    bug = _caught(_kernel, -1)
    with pytest.raises(ValueError, match="negative dimensions") as info:
        as_user_error(bug)
    assert info.value is bug and info.traceback[-1].name == "_kernel"  # its own traceback, not a new one
    # the project's own error types are the user's wherever they come from (a DataLoader worker re-raises
    # them from torch's code)
    wrapped = _caught(_raise_from_outside, DatasetError("bad label line", path="labels/000001.txt", line=3))
    assert not raised_on_purpose(wrapped)
    assert "labels/000001.txt:3" in str(as_user_error(wrapped, always=(DatasetError,)))


def _raise_from_outside(e):
    np.vectorize(lambda _: (_ for _ in ()).throw(e))([0])  # raised inside numpy's frames


def test_the_project_s_files_are_its_package_and_checkout_but_not_an_environment_inside_it(monkeypatch, tmp_path):
    root = cli._CHECKOUT
    assert is_project_file(root / "detbench" / "ops" / "cylinder.py") and is_project_file(root / "tools" / "train.py")
    assert is_project_file(__file__)
    assert not is_project_file(root / ".venv" / "lib" / "python3.11" / "site-packages" / "numpy" / "core" / "x.py")
    assert not is_project_file(np.__file__) and not is_project_file(tmp_path / "x.py")
    # installed as a package: its folder's parent is site-packages, which is not the project's
    site = tmp_path / "lib" / "site-packages"
    monkeypatch.setattr(cli, "_PACKAGE", site / "detbench")
    monkeypatch.setattr(cli, "_CHECKOUT", site)
    assert is_project_file(site / "detbench" / "train" / "loop.py")
    assert not is_project_file(site / "numpy" / "lib" / "format.py")
