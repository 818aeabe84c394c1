"""Run ``python SCRIPT ARGS`` and ``python -m MODULE ARGS`` as forks of a server that has imported torch, Lightning,
inductor, TorchRL and the project once.

A fresh interpreter spends 3-8 s of CPU importing these before a script does anything, and the suite starts scripts
many times. Each request here forks the server instead: the child gets the arguments, working directory,
environment, standard streams, ``sys.path[0]`` and exit status of a fresh interpreter and exits through the normal
interpreter shutdown (atexit handlers, non-daemon threads). What a library reads from the environment while it is
imported comes from the server's environment: the test process's, with the repository on ``PYTHONPATH``.

The server only imports; it runs no torch operation, so no thread pool exists when it forks (``serve`` checks that it
is a single thread). ``python -c`` stays a fresh interpreter: the tests that use it check what an import pulls in.
A module that works only because another one imported a submodule first would pass here, so the main job
(``test_compare_command_runs_physics_and_surrogate``) still runs in a fresh interpreter.
Used as ``run_python(argv, cwd, env, timeout)``, a drop-in for ``subprocess.run([sys.executable, *argv], ...)``
with captured text output.
"""
from __future__ import annotations

import atexit
import json
import os
import select
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PRELOAD = ("numpy", "scipy.integrate", "scipy.optimize", "torch", "torch._dynamo", "torch._inductor.compile_fx",
           "lightning.pytorch", "matplotlib.pyplot", "tensordict", "torchrl", "gymnasium", "pybullet")


def _preload() -> None:
    import importlib
    import pkgutil
    for name in PRELOAD:
        importlib.import_module(name)
    for pkg in map(importlib.import_module, ("physics", "cmlearn")):  # every module but the command-line entries
        for mod in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
            if not mod.name.endswith("__main__"):
                importlib.import_module(mod.name)


def _child(req: dict, requests, replies) -> None:
    """Become ``python ARGV`` as a fresh interpreter would; never returns."""
    import runpy
    requests.close()
    replies.close()
    os.setsid()  # a timeout kills the script with whatever it started
    for fd, path in ((1, req["stdout"]), (2, req["stderr"])):
        f = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(f, fd)
        os.close(f)
    os.chdir(req["cwd"])
    os.environ.clear()
    os.environ.update(req["env"])
    argv = req["argv"]
    if argv[0] == "-m":
        sys.argv, sys.path[0] = argv[1:], os.getcwd()
        runpy.run_module(argv[1], run_name="__main__", alter_sys=True)
    else:
        sys.argv, sys.path[0] = argv, os.path.dirname(os.path.realpath(argv[0]))
        runpy.run_path(argv[0], run_name="__main__")
    raise SystemExit(0)  # an exception or sys.exit in the script ends the child as it ends an interpreter


def serve() -> None:
    """Read one JSON request per line on stdin; answer ``{"pid": ...}`` when the child starts and ``{"rc": ...}``
    when it ends."""
    rfd, wfd = os.dup(0), os.dup(1)
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)  # the children's stdin
    os.close(null)
    os.dup2(2, 1)  # what an import prints goes to the server's stderr, not into the replies
    _preload()
    threads = len(os.listdir("/proc/self/task"))
    if threads != 1:
        raise RuntimeError(f"forked_scripts: the server has {threads} threads after its imports; forking is unsafe")
    requests, replies = os.fdopen(rfd), os.fdopen(wfd, "w", buffering=1)
    replies.write('{"ready": true}\n')
    while line := requests.readline():
        req = json.loads(line)
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            _child(req, requests, replies)
        replies.write(json.dumps({"pid": pid}) + "\n")
        _, status = os.waitpid(pid, 0)
        replies.write(json.dumps({"rc": os.waitstatus_to_exitcode(status)}) + "\n")


class _Server:
    def __init__(self) -> None:
        env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
        self.tmp = tempfile.TemporaryDirectory(prefix="forked_scripts_")
        self.log = os.path.join(self.tmp.name, "server.err")  # not the stderr of the test that happened to start it
        with open(self.log, "w") as log:
            self.proc = subprocess.Popen([sys.executable, __file__], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                         stderr=log, env=env, text=True, bufsize=1)
        if self._reply(300) != {"ready": True}:
            raise RuntimeError(f"forked_scripts: the server did not start: {Path(self.log).read_text()[-2000:]}")
        atexit.register(self.close)

    def _reply(self, timeout: float | None) -> dict | None:
        if not select.select([self.proc.stdout], [], [], timeout)[0]:
            return None
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"forked_scripts: the server ended with {self.proc.wait()}: "
                               f"{Path(self.log).read_text()[-2000:]}")
        return json.loads(line)

    def run(self, argv: list[str], cwd, env: dict, timeout: float) -> subprocess.CompletedProcess:
        out, err = (os.path.join(self.tmp.name, s) for s in ("out", "err"))  # one script at a time
        req = {"argv": [str(a) for a in argv], "cwd": str(cwd), "env": dict(env), "stdout": out, "stderr": err}
        self.proc.stdin.write(json.dumps(req) + "\n")
        self.proc.stdin.flush()
        pid = self._reply(60)["pid"]
        done = self._reply(timeout)
        if done is None:
            os.killpg(pid, signal.SIGKILL)
            self._reply(60)
            raise subprocess.TimeoutExpired([sys.executable, *argv], timeout)
        texts = []
        for path in (out, err):
            with open(path, encoding="utf-8", errors="replace") as f:
                texts.append(f.read())
            os.unlink(path)
        return subprocess.CompletedProcess([sys.executable, *argv], done["rc"], *texts)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.stdin.close()
            self.proc.wait(60)
        self.tmp.cleanup()


_server: _Server | None = None


def run_python(argv: list, cwd, env: dict | None = None, timeout: float = 600) -> subprocess.CompletedProcess:
    """``subprocess.run([sys.executable, *argv], cwd=cwd, env=env, capture_output=True, text=True,
    timeout=timeout)``, forked from the server (started on first use, one per test process); that very call for
    ``-c`` and off Linux."""
    global _server
    if argv[0] == "-c" or not sys.platform.startswith("linux"):  # forking after these imports is Linux-only here
        return subprocess.run([sys.executable, *map(str, argv)], cwd=cwd, env=env, capture_output=True, text=True,
                              timeout=timeout)
    if _server is None:
        _server = _Server()
    return _server.run(argv, cwd, os.environ if env is None else env, timeout)


if __name__ == "__main__":
    serve()
