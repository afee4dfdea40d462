"""Output transactions: the files of a case appear together or not at all.

Unit tests of :class:`BoneWatertightLib.io.files.OutputTransaction` and the run service, then
the command line against real operating-system failures (a folder as the output, a name too
long, a read-only file system, a full disk, a file-size limit) and real signals sent to real
processes (SIGTERM, SIGHUP, SIGINT, and ``kill -9`` followed by a clean run).
"""

import csv
import os
import re
import resource
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import SimpleITK as sitk

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from BoneWatertightLib.app import cli, run  # noqa: E402
from BoneWatertightLib.errors import CancelledBySignal, InputError, OutputError  # noqa: E402
from BoneWatertightLib.io import files, meshes  # noqa: E402
from BoneWatertightLib.io.files import OutputTransaction, name_from_part, name_part  # noqa: E402
from BoneWatertightLib.params import Parameters  # noqa: E402
from test_cli import FAST, sphere_ct  # noqa: E402

PYTHON = sys.executable


def listing(folder):
    """Every name in ``folder`` and below, relative, sorted (hidden files included)."""
    found = []
    for dirpath, dirnames, filenames in os.walk(folder):
        rel = os.path.relpath(dirpath, folder)
        found += [os.path.normpath(os.path.join(rel, n)) for n in filenames]
    return sorted(found)


def dead_pid():
    child = subprocess.Popen([PYTHON, "-c", "pass"])
    child.wait()
    return child.pid


# ---------------------------------------------------------------------------- the transaction

def test_files_appear_only_at_commit(tmp_path):
    with OutputTransaction() as tx:
        for path in ("a.txt", "new/deeper/b.txt", "c.json"):
            files.write_text(path, str(tmp_path / path), transaction=tx)
        staged = listing(tmp_path)
        assert len(staged) == 3 and all(os.path.basename(p).startswith(".") for p in staged)
        assert all(files.is_temporary_name(os.path.basename(p)) for p in staged)
    assert listing(tmp_path) == ["a.txt", "c.json", "new/deeper/b.txt"]
    assert (tmp_path / "new/deeper/b.txt").read_text() == "new/deeper/b.txt"


def test_abort_removes_staged_files_and_new_folders_keeps_old_files(tmp_path):
    (tmp_path / "a.txt").write_text("previous")
    with pytest.raises(KeyboardInterrupt):
        with OutputTransaction() as tx:
            files.write_text("new", str(tmp_path / "a.txt"), transaction=tx)
            files.write_text("new", str(tmp_path / "made/for/b.txt"), transaction=tx)
            raise KeyboardInterrupt
    assert listing(tmp_path) == ["a.txt"] and os.listdir(tmp_path) == ["a.txt"]
    assert (tmp_path / "a.txt").read_text() == "previous"


def test_discard_to_a_mark_drops_later_files_and_their_new_folders(tmp_path):
    with OutputTransaction() as tx:
        files.write_text("a", str(tmp_path / "a.txt"), transaction=tx)
        mark = tx.mark()
        files.write_text("b", str(tmp_path / "new/b.txt"), transaction=tx)
        files.write_text("c", str(tmp_path / "c.txt"), transaction=tx)
        tx.discard(mark)
        assert tx.paths == [str(tmp_path / "a.txt")]
    assert listing(tmp_path) == ["a.txt"] and os.listdir(tmp_path) == ["a.txt"]


def test_a_rename_that_fails_rolls_back_the_ones_done(tmp_path):
    (tmp_path / "a.txt").write_text("old a")
    (tmp_path / "b.txt").write_text("old b")
    tx = OutputTransaction()
    files.write_text("new a", str(tmp_path / "a.txt"), transaction=tx)
    files.write_text("new b", str(tmp_path / "b.txt"), transaction=tx)
    # b.txt turns into a folder after staging: its rename fails after a.txt's succeeded
    os.remove(tmp_path / "b.txt")
    os.mkdir(tmp_path / "b.txt")
    with pytest.raises(OutputError, match=r"Cannot write .*b\.txt: Is a directory; give a file "
                                          "name, not a folder"):
        tx.commit()
    assert (tmp_path / "a.txt").read_text() == "old a"
    assert sorted(os.listdir(tmp_path)) == ["a.txt", "b.txt"]
    assert os.listdir(tmp_path / "b.txt") == []
    assert tx.state == "aborted"


def test_an_empty_staged_file_fails_the_commit(tmp_path):
    with pytest.raises(OutputError, match="the writer produced no data"):
        with OutputTransaction() as tx:
            files.write_text("x", str(tmp_path / "a.txt"), transaction=tx)
            tx.stage(str(tmp_path / "b.txt"))  # never written
    assert os.listdir(tmp_path) == []


def test_stage_refuses_what_cannot_be_a_file(tmp_path):
    (tmp_path / "folder.stl").mkdir()
    (tmp_path / "plain").write_text("a file")
    tx = OutputTransaction()
    with pytest.raises(OutputError, match="folder.stl: it is a folder; give a file name"):
        tx.stage(str(tmp_path / "folder.stl"))
    with pytest.raises(OutputError, match=r"the file name is 304 bytes long, the file system "
                                          r"allows 255; choose a shorter name"):
        tx.stage(str(tmp_path / ("x" * 300 + ".stl")))
    with pytest.raises(OutputError, match="plain is a file, not a folder"):
        tx.stage(str(tmp_path / "plain" / "a.stl"))
    tx.stage(str(tmp_path / "a.stl"))
    with pytest.raises(InputError, match="Two outputs of this run are the same file"):
        tx.stage(str(tmp_path / "." / "a.stl"))
    tx.abort()
    assert sorted(os.listdir(tmp_path)) == ["folder.stl", "plain"]


def test_a_name_at_the_limit_still_gets_a_temporary_file(tmp_path):
    name = "y" * 251 + ".stl"  # 255 bytes: the temporary name must be shortened, not fail
    with OutputTransaction() as tx:
        files.write_text("ok", str(tmp_path / name), transaction=tx)
    assert os.listdir(tmp_path) == [name]


def test_stale_temporary_files_are_removed_live_ones_kept(tmp_path):
    host = files._HOST
    other = "0" * 6 if host != "0" * 6 else "1" * 6
    sleeper = subprocess.Popen([PYTHON, "-c", "import time; time.sleep(60)"])
    try:
        names = {
            "dead": f".bone.stl.{host}-{dead_pid()}-0123abcd.part.stl",
            "dead_backup": f".bone.stl.{host}-{dead_pid()}-0123abcd.prev.stl",
            "alive": f".bone.stl.{host}-{sleeper.pid}-0123abcd.part.stl",
            "other_host_fresh": f".bone.stl.{other}-{dead_pid()}-0123abcd.part.stl",
            "other_host_old": f".bone.stl.{other}-{dead_pid()}-4567abcd.part.stl",
            "old_version_fresh": ".bone.stl.89abcdef.part.stl",
            "old_version_old": ".report.json.0011aabb.part.json",
            "unrelated": ".hidden_notes.part",
        }
        for key, name in names.items():
            (tmp_path / name).write_text(key)
        two_days_ago = time.time() - 2 * 24 * 3600
        for key in ("other_host_old", "old_version_old"):
            os.utime(tmp_path / names[key], (two_days_ago, two_days_ago))
        with OutputTransaction() as tx:  # staging into the folder sweeps it
            files.write_text("new", str(tmp_path / "bone.stl"), transaction=tx)
        left = set(os.listdir(tmp_path))
        assert left == {"bone.stl", names["alive"], names["other_host_fresh"],
                        names["old_version_fresh"], names["unrelated"]}
    finally:
        sleeper.kill()
        sleeper.wait()


def test_a_signal_during_the_commit_waits_for_its_end(tmp_path):
    """A real SIGTERM sent inside the critical section is acted on only after it."""
    with run.cancel_on_signals():
        tx = OutputTransaction()
        files.write_text("a", str(tmp_path / "a.txt"), transaction=tx)
        with pytest.raises(CancelledBySignal) as info:
            with files.critical_section():
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.05)  # the handler has run by now, and deferred
                tx.commit()
        assert info.value.name == "SIGTERM"
    assert os.listdir(tmp_path) == ["a.txt"]
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL


# ---------------------------------------------------------------------------- file names

TRICKY = [".", "..", "...", "", "a b", "a_b", "a%20b", "a/b", "a\\b", "a:b", "../etc", "femur",
          "Femur", ".hidden", "x.", "%", "%2E", "_", "é", "e\u0301", "a\nb", "a\x00b",
          "segment", "femur left", "femur_left"]


def test_name_parts_are_one_to_one_and_safe():
    parts = [name_part(t) for t in TRICKY]
    assert len(set(parts)) == len(TRICKY)
    for text, part in zip(TRICKY, parts):
        assert name_from_part(part) == text
        assert part and "/" not in part and "\\" not in part and not part.startswith(".")
        assert part not in (".", "..") and part.isascii() and part.isprintable()
    assert name_part(".") == "%2E" and name_part("..") == "%2E."
    assert name_part("femur left") == "femur%20left" and name_part("femur_left") == "femur_left"


def test_dot_segments_write_different_files(tmp_path):
    """Before: '.' and '..' both became 'segment' and overwrote each other."""
    outs = {run.fill_template(str(tmp_path / "bone_{label}.stl"), name) for name in (".", "..")}
    assert len(outs) == 2
    with OutputTransaction() as tx:
        for out in outs:
            files.write_text(out, out, transaction=tx)
    assert sorted(os.listdir(tmp_path)) == ["bone_%2E..stl", "bone_%2E.stl"]


# ---------------------------------------------------------------------------- the run service

@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    """The CLI tests' sphere case on disk and its real reconstruction (with intermediates)."""
    from BoneWatertightLib.pipeline import reconstruct

    folder = tmp_path_factory.mktemp("sphere")
    ct, mask = sphere_ct()
    sitk.WriteImage(ct, str(folder / "ct.nrrd"))
    sitk.WriteImage(mask, str(folder / "mask.nrrd"))
    params = Parameters(spacing=1.0, iterations=3, poisson_depth=6, views=6,
                        keep_intermediates=True).validate()
    result = reconstruct(ct, mask, params)
    return {"folder": folder, "ct": ct, "mask": mask, "params": params,
            "reconstruct": lambda *args: result}


def run_sphere(sphere, out, **kwargs):
    return run.run_case(sphere["ct"], sphere["mask"], "bone", str(out), sphere["params"],
                        reconstruct=sphere["reconstruct"], **kwargs)


def test_every_output_of_a_case_appears_together(sphere, tmp_path):
    report = run_sphere(sphere, tmp_path / "bone.stl", also=[str(tmp_path / "bone.vtp")],
                        intermediates_dir=str(tmp_path / "inter"),
                        report_path=str(tmp_path / "r/report.json"))
    names = listing(tmp_path)
    assert "bone.stl" in names and "bone.vtp" in names and "r/report.json" in names
    assert len([n for n in names if n.startswith("inter/")]) == 6
    assert not [n for n in names if files.is_temporary_name(os.path.basename(n))]
    assert report.output.report == str(tmp_path / "r/report.json")
    assert sorted(report.output.intermediates) == sorted(
        str(tmp_path / n) for n in names if n.startswith("inter/"))


def test_a_failed_report_write_leaves_no_surface(sphere, tmp_path):
    """Before: the surface was written, then the report failed (exit 1)."""
    (tmp_path / "bone.stl").write_bytes(b"earlier result")
    (tmp_path / "report.json").mkdir()
    with pytest.raises(OutputError, match="report.json: it is a folder"):
        run_sphere(sphere, tmp_path / "bone.stl", also=[str(tmp_path / "new/bone.vtp")],
                   intermediates_dir=str(tmp_path / "inter"),
                   report_path=str(tmp_path / "report.json"))
    assert listing(tmp_path) == ["bone.stl"]
    assert sorted(os.listdir(tmp_path)) == ["bone.stl", "report.json"]
    assert (tmp_path / "bone.stl").read_bytes() == b"earlier result"


def test_a_failed_intermediate_leaves_nothing(sphere, tmp_path, monkeypatch):
    def broken(poly, tmp, system):
        with open(tmp, "wb") as f:
            f.write(b"half")
        raise OSError(28, "No space left on device")

    monkeypatch.setitem(meshes._WRITERS, ".ply", broken)
    with pytest.raises(OutputError, match=r"Cannot write .*inter/bone_P_H0.ply: No space left on "
                                          "device; free some space"):
        run_sphere(sphere, tmp_path / "bone.stl", intermediates_dir=str(tmp_path / "inter"))
    assert os.listdir(tmp_path) == []


def test_a_shared_transaction_keeps_the_cases_that_succeeded(sphere, tmp_path):
    with OutputTransaction() as tx:
        run_sphere(sphere, tmp_path / "one.stl", transaction=tx)
        (tmp_path / "two.json").mkdir()
        with pytest.raises(OutputError):
            run_sphere(sphere, tmp_path / "two.stl", report_path=str(tmp_path / "two.json"),
                       transaction=tx)
        assert tx.paths == [str(tmp_path / "one.stl")]
    assert sorted(os.listdir(tmp_path)) == ["one.stl", "two.json"]


# ---------------------------------------------------------------------------- the CLI: OS errors

def cli_run(sphere, out, capfd, *extra):
    """The CLI in this process; stderr as the file descriptor saw it (VTK's C++ output too)."""
    folder = sphere["folder"]
    code = cli.main(["--ct", str(folder / "ct.nrrd"), "--seg", str(folder / "mask.nrrd"),
                     "--label", "1", "--out", str(out)] + list(extra) + FAST)
    err = capfd.readouterr().err
    return code, err


def one_error_line(err):
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


def test_cli_report_into_a_folder_exit_5_no_surface(sphere, tmp_path, capfd):
    (tmp_path / "r.json").mkdir()
    code, err = cli_run(sphere, tmp_path / "b.stl", capfd, "--report", str(tmp_path / "r.json"))
    assert code == 5 and "r.json: it is a folder" in one_error_line(err)
    assert os.listdir(tmp_path) == ["r.json"]


def test_cli_out_is_a_folder_and_name_too_long(sphere, tmp_path, capfd):
    (tmp_path / "b.stl").mkdir()
    code, err = cli_run(sphere, tmp_path / "b.stl", capfd)
    assert code == 5 and "it is a folder" in one_error_line(err)
    code, err = cli_run(sphere, tmp_path / ("n" * 300 + ".stl"), capfd)
    assert code == 5 and "file name is 304 bytes long" in one_error_line(err)
    (tmp_path / "plain").write_text("x")
    code, err = cli_run(sphere, tmp_path / "plain" / "b.stl", capfd)
    assert code == 5 and "plain is a file, not a folder" in one_error_line(err)
    assert sorted(os.listdir(tmp_path)) == ["b.stl", "plain"]


def mount_tmpfs(folder, options):
    """Mount a tmpfs on ``folder`` (root only); skip the test where that is impossible."""
    os.makedirs(folder, exist_ok=True)
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)],
                          capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
    return folder


@pytest.fixture()
def mounts():
    mounted = []
    yield mounted
    for folder in reversed(mounted):
        subprocess.run(["umount", str(folder)], check=False)


def test_cli_read_only_folder_exit_5(sphere, tmp_path, capfd, mounts):
    folder = tmp_path / "ro"
    if os.geteuid() == 0:
        mounts.append(mount_tmpfs(folder, "ro,size=1m"))
        reason = "Read-only file system"
    else:
        folder.mkdir()
        folder.chmod(0o555)
        reason = "Permission denied"
    code, err = cli_run(sphere, folder / "b.stl", capfd, "--report", str(folder / "r.json"))
    assert code == 5 and reason in one_error_line(err), err
    assert os.listdir(folder) == []


def test_cli_disk_full_exit_5_earlier_file_kept(sphere, tmp_path, capfd, mounts):
    folder = mount_tmpfs(tmp_path / "full", "size=64k")
    mounts.append(folder)
    (folder / "b.stl").write_bytes(b"earlier")
    code, err = cli_run(sphere, folder / "b.stl", capfd, "--report", str(folder / "r.json"))
    line = one_error_line(err)
    assert code == 5 and "No space left on device; free some space" in line, err
    assert os.listdir(folder) == ["b.stl"] and (folder / "b.stl").read_bytes() == b"earlier"


def test_cli_file_size_limit_exit_5(sphere, tmp_path):
    """A real EFBIG (ulimit -f) in a real process: works without root."""
    folder = sphere["folder"]

    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (20000, 20000))

    done = subprocess.run(
        [PYTHON, "-m", "BoneWatertightLib", "--ct", str(folder / "ct.nrrd"),
         "--seg", str(folder / "mask.nrrd"), "--label", "1", "--out", str(tmp_path / "b.stl"),
         "--report", str(tmp_path / "r.json")] + FAST,
        cwd=ROOT, capture_output=True, text=True, timeout=300, preexec_fn=limit)
    assert done.returncode == 5, done.stderr
    assert "File too large" in one_error_line(done.stderr)
    assert os.listdir(tmp_path) == []


# ---------------------------------------------------------------------------- real signals

DRIVER = """\
import os, sys, time
sys.path.insert(0, {root!r})
from BoneWatertightLib.io import meshes

_real = meshes._WRITERS[".stl"]


def slow(poly, tmp, system):
    # the whole file, then a long pause: the signal arrives while outputs are staged
    _real(poly, tmp, system)
    print("WRITING", os.getpid(), flush=True)
    time.sleep(120)


meshes._WRITERS[".stl"] = slow  # at import: spawned batch workers run this too

if __name__ == "__main__":
    from BoneWatertightLib.app import cli
    sys.exit(cli.main(sys.argv[1:]))
"""


def start_driver(tmp_path, args):
    driver = tmp_path / "driver.py"
    driver.write_text(DRIVER.format(root=ROOT))
    return subprocess.Popen([PYTHON, str(driver)] + args, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=str(tmp_path))


def wait_for_lines(process, prefix, count, seconds=240):
    """Read stdout until ``prefix`` and the word after it were printed ``count`` times; each
    as the line "``prefix`` word". Found anywhere in a line: the workers and the batch share
    the pipe, and a clean-clone run (stop 47) read one of the two workers' lines and then the
    batch's normal end - as when a line lands after another process's unterminated output."""
    found = []
    pattern = re.compile(re.escape(prefix) + r" \S+")

    def read():
        for line in process.stdout:
            found.extend(match + "\n" for match in pattern.findall(line))
            if len(found) >= count:
                return

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    reader.join(seconds)
    if len(found) < count:
        process.kill()
        raise AssertionError(f"only {len(found)} '{prefix}' lines; stderr: "
                             f"{process.stderr.read()}")
    return found


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT])
def test_signal_during_the_write_exit_130_no_file(sphere, tmp_path, signum):
    """Before: SIGTERM had no handler (exit -15) and left .part files."""
    folder = sphere["folder"]
    out = tmp_path / "out"
    process = start_driver(tmp_path, [
        "--ct", str(folder / "ct.nrrd"), "--seg", str(folder / "mask.nrrd"), "--label", "1",
        "--out", str(out / "b.stl"), "--report", str(out / "r.json"),
        "--save-intermediates", str(out / "inter")] + FAST)
    wait_for_lines(process, "WRITING", 1)
    assert listing(out)  # staged files exist now
    process.send_signal(signum)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 130, stderr
    name = signal.Signals(signum).name
    assert f"error: cancelled ({name}); no output file was written." in stderr
    assert listing(out) == [] and not os.path.exists(out)


def test_sigterm_stops_a_batch_and_its_workers(sphere, tmp_path):
    if not os.path.isdir("/proc"):
        pytest.skip("needs /proc to tell the workers apart from later processes")
    folder = sphere["folder"]
    out = tmp_path / "out"
    with open(tmp_path / "cases.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["case", "ct", "seg", "label", "out"])
        for case in ("a", "b"):
            writer.writerow([case, folder / "ct.nrrd", folder / "mask.nrrd", "1",
                             out / f"{case}.stl"])
    process = start_driver(tmp_path, ["--cases", str(tmp_path / "cases.csv"), "--workers", "2",
                                      "--report", str(out / "{case}.json"),
                                      "--summary", str(tmp_path / "summary.csv")] + FAST)
    pids = [int(line.split()[1]) for line in wait_for_lines(process, "WRITING", 2)]
    assert len(set(pids)) == 2 and process.pid not in pids  # both writing, in the workers
    workers = {pid: process_start(pid) for pid in pids}
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 130, stderr
    assert "error: cancelled (SIGTERM): 0 of 2 cases had finished" in stderr, stderr
    assert listing(out) == [], (listing(out), stderr)
    assert not os.path.exists(tmp_path / "summary.csv"), stderr
    for pid, start in workers.items():  # the workers are gone
        assert start is not None and process_start(pid) != start, (pid, stderr)


def process_start(pid):
    """The start time of the running (not zombie) process ``pid``, or None: tells a process
    from a later one that got the same number."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return None if fields[0] == "Z" else int(fields[19])


def test_sigterm_during_the_commit_is_acted_on_after_it(sphere, tmp_path, capfd, monkeypatch):
    """A real SIGTERM that arrives while the files are being renamed: every file is renamed,
    then the run stops with exit code 130 and says the outputs are complete."""
    backup = files.OutputTransaction._backup
    sent = []

    def signal_then_backup(self, final):
        if not sent:
            sent.append(final)
            os.kill(os.getpid(), signal.SIGTERM)
        return backup(self, final)

    monkeypatch.setattr(files.OutputTransaction, "_backup", signal_then_backup)
    code, err = cli_run(sphere, tmp_path / "b.stl", capfd, "--report", str(tmp_path / "r.json"))
    assert sent and code == 130
    assert "cancelled (SIGTERM) just after the outputs were written; they are complete" in err
    assert sorted(os.listdir(tmp_path)) == ["b.stl", "r.json"]
    assert meshes.read_surface(str(tmp_path / "b.stl")).n_faces > 100


def test_kill_9_leftovers_are_removed_by_the_next_run(sphere, tmp_path, capfd):
    folder = sphere["folder"]
    out = tmp_path / "out"
    process = start_driver(tmp_path, [
        "--ct", str(folder / "ct.nrrd"), "--seg", str(folder / "mask.nrrd"), "--label", "1",
        "--out", str(out / "b.stl")] + FAST)
    wait_for_lines(process, "WRITING", 1)
    process.kill()
    process.communicate(timeout=60)
    left = os.listdir(out)
    assert len(left) == 1 and files.is_temporary_name(left[0]) and f"-{process.pid}-" in left[0]
    code, err = cli_run(sphere, out / "b.stl", capfd)
    assert code == 0, err
    assert os.listdir(out) == ["b.stl"]
    assert meshes.read_surface(str(out / "b.stl")).n_faces > 100


def test_cli_labels_share_one_transaction(sphere, tmp_path, capfd):
    """Two labels and one report: label 2 fails (no bone there), so label 1's surface and the
    report are committed together and label 2 leaves nothing."""
    folder = sphere["folder"]
    labels = sitk.GetArrayFromImage(sphere["mask"]).astype(np.uint8)
    labels[1:4, 1:4, 1:4] = 2  # soft tissue in a corner: no voxel in the threshold window
    image = sitk.GetImageFromArray(labels)
    image.CopyInformation(sphere["mask"])
    sitk.WriteImage(image, str(tmp_path / "labels.nrrd"))
    code = cli.main(["--ct", str(folder / "ct.nrrd"), "--seg", str(tmp_path / "labels.nrrd"),
                     "--label", "1", "--label", "2", "--out", str(tmp_path / "o/b_{label}.stl"),
                     "--report", str(tmp_path / "o/r.json")] + FAST)
    err = capfd.readouterr().err
    # partly done (issue 21): label 1 written, label 2 named with its reason
    assert code == 6 and err.startswith("error: 2: ") and err.count("\n") == 1, err
    assert sorted(os.listdir(tmp_path / "o")) == ["b_1.stl", "r.json"]
