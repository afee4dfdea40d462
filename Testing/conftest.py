"""Make the repository root importable (``import BoneWatertightLib``) when running pytest."""

import os
import sys

import pytest

_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if _ROOT not in sys.path:
    sys.path.insert(0, _ROOT)


@pytest.fixture(autouse=True)
def _helper_processes_as_the_library_default():
    """The command line allows helper processes for its own process
    (app.run.configure_own_process); tests that call it in this process must not leave that on
    for the tests after them."""
    from BoneWatertightLib import threads

    before = threads.helper_processes_allowed()
    yield
    threads.allow_helper_processes(before)
