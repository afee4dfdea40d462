"""Bones worked at once (pipeline._Run.each on threads): same results, the caller's progress
callback on the calling thread only, cancel and failures as in the sequential loop, and the
thread count bounded by the memory limit."""

import threading
import types

import numpy as np
import pytest

from BoneWatertightLib import pipeline
from BoneWatertightLib.errors import CancelledError, ReconstructionError
from BoneWatertightLib.params import Parameters
from BoneWatertightLib.progress import Progress


def _run(threads, callback=None, keep_going=False):
    run = pipeline._Run(Parameters(), Progress(callback), keep_going)
    run.threads = threads
    return run


def test_bones_run_at_once_and_give_what_the_sequential_loop_gives():
    barrier = threading.Barrier(2, timeout=10)  # passes only if two bones run at once

    def work(k, part):
        part(0.5, f"bone {k}")
        if k in (1, 2):
            barrier.wait()
        part(1.0, f"bone {k} done")
        return k * k

    threaded = _run(2).each([1, 2, 3], Progress(), work)
    sequential = _run(1).each([1, 2, 3], Progress(), lambda k, part: k * k)
    assert threaded == sequential == {1: 1, 2: 4, 3: 9}
    assert list(threaded) == [1, 2, 3]


def test_the_callers_callback_runs_on_the_calling_thread_and_ends_at_one():
    calls = []
    main = threading.current_thread()

    def callback(fraction, message):
        calls.append((threading.current_thread() is main, fraction, message))

    run = _run(2, callback)

    def work(k, part):
        for i in range(5):
            part(i / 4, f"bone {k} step {i}")
            threading.Event().wait(0.05)
        return k

    run.each([1, 2, 3, 4], run.progress, work)
    assert calls and all(on_main for on_main, _, _ in calls)
    fractions = [f for _, f, _ in calls]
    assert fractions == sorted(fractions)  # never goes back
    assert fractions[-1] == pytest.approx(1.0)
    # every message of every bone reaches the callback, each bone's in its order
    for k in (1, 2, 3, 4):
        mine = [m for _, _, m in calls if m.startswith(f"bone {k} ")]
        assert mine == [f"bone {k} step {i}" for i in range(5)]


def test_cancel_stops_the_bones_still_running():
    stopped = []

    def callback(fraction, message):
        return fraction < 0.1  # the user cancels early

    run = _run(2, callback)

    def work(k, part):
        try:
            for i in range(200):
                part(i / 200, f"bone {k}")
                threading.Event().wait(0.02)
        except CancelledError:
            stopped.append(k)
            raise
        return k

    with pytest.raises(CancelledError):
        run.each([1, 2], run.progress, work)
    assert sorted(stopped) == [1, 2]  # both stopped at a progress step, not after 4 s


@pytest.mark.parametrize("keep_going", [False, True])
def test_a_failing_bone_fails_the_run_or_only_itself(keep_going):
    def work(k, part):
        if k == 2:
            raise ReconstructionError("bone 2 is bad")
        for i in range(20):
            part(i / 20)
            threading.Event().wait(0.01)
        return k

    run = _run(2, keep_going=keep_going)
    if not keep_going:
        with pytest.raises(ReconstructionError, match="bone 2 is bad"):
            run.each([1, 2, 3], run.progress, work)
    else:
        out = run.each([1, 2, 3], run.progress, work)
        assert out == {1: 1, 3: 3}
        assert list(run.failed) == [2] and "bone 2" in str(run.failed[2])
        # a failed bone is not worked again by the next stage
        assert run.each([1, 2, 3], run.progress, lambda k, part: -k) == {1: -1, 3: -3}


@pytest.mark.parametrize("budget, expected", [(2.5, 2), (1.5, 1), (-1.0, 1)])
def test_bones_at_once_fit_the_memory_budget(budget, expected):
    """Costs 1 per bone: a budget of 2.5 lets two run at once, 1.5 one (and a budget that
    nothing fits still runs every bone, one at a time)."""
    lock = threading.Lock()
    running, most = [0], [0]

    def work(k, part):
        with lock:
            running[0] += 1
            most[0] = max(most[0], running[0])
        threading.Event().wait(0.1)
        with lock:
            running[0] -= 1
        return k

    run = _run(2)
    run.costs = {k: 1.0 for k in range(1, 6)}
    run.budget = budget
    assert run.each([1, 2, 3, 4, 5], run.progress, work) == {k: k for k in range(1, 6)}
    assert most[0] == expected


def test_bone_schedule_charges_each_bone_its_box(monkeypatch):
    monkeypatch.setattr(pipeline.os, "cpu_count", lambda: 8)
    box = (slice(0, 100), slice(0, 100), slice(0, 50))  # 5e5 voxels
    own = types.SimpleNamespace(regions={k: (box, None) for k in (1, 2, 3)})
    prep = types.SimpleNamespace(targets=[1, 3], info={"estimated_memory_gb": 1.0})
    ws = types.SimpleNamespace(own=own, prep=prep, targets=prep.targets)
    threads, costs, budget = pipeline.bone_schedule(ws, 4.0)
    assert threads == 2  # two targets
    assert costs == {1: 5e5 * pipeline._prepare.BYTES_PER_VOXEL,
                     3: 5e5 * pipeline._prepare.BYTES_PER_VOXEL}
    held = pipeline._held_bytes()
    assert held is not None and held > 10e6  # this process holds some memory
    assert budget == pytest.approx(4.0 * 1024 ** 3 - held, rel=0.05)
