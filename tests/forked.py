"""Real `python -m ggns ...` processes without a Python start-up each, for the fault tests
(tests/test_faults.py): a forkserver that imported ggns's command line, Lightning and torch once forks
one child per command, and the child runs `ggns.__main__.main` on the command's arguments, with the
command's environment and working directory, its stdout and stderr in files. The child is a process
of its own: its own pid, exit status and signals (a SIGKILL ends it where it is), its own memory; only
the imports are shared, which saves about 10 s of CPU per command on the 2-core machine (the start-up
of `python -m ggns fit` is mostly imports, docs/results/test_durations/import_time.txt). The
checkpoints, logs and parts that the tests compare are written by the child and read back from disk,
as with a process started from scratch.

Not covered here, and so left to real start-ups elsewhere: the interpreter's own start (`python -m
ggns` resolving the package; test_cli, test_install), what a process inherits besides its environment
(test_distributed's DDP ranks, test_bad_input's sweep and bench learning fits).

A sweep (`start(..., session=True)`) is forked into a session of its own, so that a SIGKILL to its
process group ends it and whatever it runs, as a cluster ends a job; each fit and test it runs is forked
from it in turn (`_ForkingSubprocess`), so none of them imports torch and Lightning again either."""
from __future__ import annotations

import multiprocessing
import os
import signal
import subprocess
import sys
from pathlib import Path

# imported once by the forkserver (one that is missing is skipped: open3d where a machine has none)
PRELOAD = ["ggns.__main__", "ggns.cli.lightning", "ggns.data.generate", "ggns.sweeps.sweep", "open3d", "kill_points",
           "forked"]


def _main(argv: list[str], env: dict[str, str], cwd: str, stdout: str, stderr: str, session: bool = False) -> None:
    """The child: `python -m ggns <argv>` from here on; ends the process with main()'s exit status.
    session: a session and process group of its own, its sweep's fits and tests forked from it."""
    if session:
        os.setsid()
        import ggns.sweeps.sweep

        ggns.sweeps.sweep.subprocess = _ForkingSubprocess  # what launch_process runs each command with
    for fd, path in ((1, stdout), (2, stderr)):
        target = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        os.dup2(target, fd)
        os.close(target)
    _run_main(argv, env, cwd)


def _run_main(argv: list[str], env: dict[str, str], cwd: str) -> None:
    """`ggns.__main__.main(argv)` in this process with `env` and `cwd`, then the process's end with its status."""
    os.environ.clear()
    os.environ.update(env)
    os.chdir(cwd)
    import torch

    from ggns.__main__ import main

    if "OMP_NUM_THREADS" in env:  # read by torch when a process starts: the forkserver read its own
        torch.set_num_threads(int(env["OMP_NUM_THREADS"]))
    sys.argv = [str(Path(sys.modules["ggns.__main__"].__file__)), *argv]
    code = 0
    try:
        main(argv)
    except SystemExit as stop:
        code = stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)
    except BaseException:  # an uncaught error: its traceback on stderr and status 1, as Python ends
        import traceback

        traceback.print_exc()
        code = 1
    import atexit

    atexit._run_exitfuncs()  # what the interpreter runs at exit (multiprocessing's children skip it)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


class _ForkingSubprocess:
    """Stands in for the `subprocess` module inside a forked sweep: `run` forks the sweep's process (its
    imports done) for each `python -m ggns fit|test` command, stdout and stderr into the run's log file."""

    STDOUT = subprocess.STDOUT

    @staticmethod
    def run(command: list[str], stdout, stderr, env: dict[str, str]) -> subprocess.CompletedProcess:
        assert command[1:3] == ["-m", "ggns"] and stderr == subprocess.STDOUT, command
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:  # the child never returns into the sweep: any failure ends it with status 1
            try:
                for fd in (1, 2):
                    os.dup2(stdout.fileno(), fd)
                _run_main(command[3:], env, os.getcwd())
            except BaseException:
                import traceback

                traceback.print_exc()
            finally:
                os._exit(1)
        _, status = os.waitpid(pid, 0)
        return subprocess.CompletedProcess(command, os.waitstatus_to_exitcode(status))


class Child:
    """One forked `python -m ggns ...`: `pid`, `poll()`, `wait()`, and its output once it ended."""

    def __init__(self, process: multiprocessing.Process, command: list[str], stdout: Path, stderr: Path,
                 session: bool = False):
        self.process, self.command, self.stdout_path, self.stderr_path = process, command, stdout, stderr
        self.session = session  # its own process group: a kill goes to all it runs

    @property
    def pid(self) -> int:
        return self.process.pid

    def poll(self) -> int | None:
        return self.process.exitcode

    def wait(self, timeout: float | None = None) -> int:
        """The exit status (negative: the signal that ended it); past `timeout` the child is killed, as
        `subprocess.run` does, and TimeoutExpired raised."""
        self.process.join(timeout)
        if self.process.exitcode is None:
            if self.session:
                os.killpg(self.process.pid, signal.SIGKILL)
            else:
                self.process.kill()
            self.process.join()
            raise subprocess.TimeoutExpired(self.command, timeout)
        return self.process.exitcode

    def result(self, timeout: float | None = None) -> subprocess.CompletedProcess:
        code = self.wait(timeout)
        return subprocess.CompletedProcess(self.command, code, self.stdout_path.read_text(),
                                           self.stderr_path.read_text())


_context = None


def start(command: list[str], output: Path, env: dict[str, str] | None = None, cwd: str | Path | None = None,
          session: bool = False) -> Child:
    """Fork `command` (`[sys.executable, "-m", "ggns", ...]`) from the forkserver; its stdout and stderr go to
    files in `output` (a fresh directory per command). env: its whole environment (default: this one's).
    session: a session of its own (`os.killpg(child.pid, ...)` reaches all it runs), a sweep's fits and tests
    forked from it."""
    global _context
    assert command[1:3] == ["-m", "ggns"], command
    if _context is None:
        _context = multiprocessing.get_context("forkserver")
        _context.set_forkserver_preload(PRELOAD)
    output = Path(output)
    output.mkdir(parents=True, exist_ok=False)
    stdout, stderr = output / "stdout", output / "stderr"
    process = _context.Process(target=_main, args=(command[3:], dict(os.environ if env is None else env),
                                                   str(cwd or os.getcwd()), str(stdout), str(stderr), session))
    process.start()
    return Child(process, command, stdout, stderr, session)


def run(command: list[str], output: Path, env: dict[str, str] | None = None, cwd: str | Path | None = None,
        timeout: float = 300) -> subprocess.CompletedProcess:
    """`subprocess.run(command, capture_output=True, text=True)` through the forkserver."""
    return start(command, output, env, cwd).result(timeout)
