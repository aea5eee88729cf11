"""Real processes of a distributed run for the tests: mavsim, the coordinator and agents, each
a ``python -m btmission`` child on 127.0.0.1, ended by its PID; and a TCP proxy that can cut
an agent's link to the coordinator."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from tests.mavlink_helpers import free_port

ME = [sys.executable, "-m", "btmission"]


def read_log(path: Path) -> list[dict[str, Any]]:
    """The events of a JSONL log being written (a cut last line is left out)."""
    out = []
    try:
        text = path.read_text()
    except FileNotFoundError:
        return []
    for line in text.splitlines():
        try:
            out.append(json.loads(line))
        except ValueError:
            pass
    return out


def wait_for(what: str, pred: Callable[[], Any], timeout_s: float, every_s: float = 0.2) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        got = pred()
        if got:
            return got
        time.sleep(every_s)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


class Fleet:
    """The processes of one distributed run of ``mission`` (all on loopback)."""

    def __init__(self, directory: Path, mission: str, speed: float) -> None:
        self.dir = directory
        self.mission = mission
        self.speed = speed
        self.port = free_port(socket.SOCK_STREAM)
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.procs: dict[str, subprocess.Popen[str]] = {}
        self._files: list[Any] = []

    def _start(self, name: str, argv: list[str]) -> subprocess.Popen[str]:
        out = (self.dir / f"{name}.out").open("w")
        self._files.append(out)
        proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, text=True)
        self.procs[name] = proc
        return proc

    def output(self, name: str) -> str:
        return (self.dir / f"{name}.out").read_text()

    def _ready(self, name: str, prefix: str, timeout_s: float) -> None:
        proc = self.procs[name]

        def ready() -> bool:
            if proc.poll() is not None:
                raise AssertionError(f"{name} exited {proc.returncode}:\n{self.output(name)}")
            return any(line.startswith(prefix) for line in self.output(name).splitlines())

        wait_for(f"{name} to say '{prefix}'", ready, timeout_s)

    def start_mavsim(self) -> None:
        self._start("mavsim", [*ME, "mavsim", "--mission", self.mission,
                               "--speed", str(self.speed), "--quiet"])  # fmt: skip
        self._ready("mavsim", "ready", 60)

    def start_coordinator(self, name: str = "coordinator", *extra: str) -> None:
        self._start(name, [*ME, "coordinator", self.mission, "--listen", self.endpoint,
                           "--log-file", str(self.dir / f"{name}.jsonl"),
                           "--speed", str(self.speed), "--quiet", *extra])  # fmt: skip
        self._ready(name, "coordinator of", 60)

    def start_agent(self, agent: str, name: str | None = None, endpoint: str | None = None) -> None:
        name = name or agent
        self._start(name, [*ME, "agent", self.mission, "--id", agent,
                           "--connect", endpoint or self.endpoint,
                           "--log-file", str(self.dir / f"{name}.jsonl"),
                           "--speed", str(self.speed), "--quiet"])  # fmt: skip

    def start_all(self, agents: tuple[str, ...] = ("R1", "R2")) -> None:
        """mavsim, the coordinator, and one process per agent."""
        self.start_mavsim()
        self.start_coordinator()
        for agent in agents:
            self.start_agent(agent)

    def log(self, name: str) -> list[dict[str, Any]]:
        return read_log(self.dir / f"{name}.jsonl")

    def wait_exit(self, name: str, timeout_s: float) -> int:
        return self.procs[name].wait(timeout_s)

    def signal(self, name: str, sig: int) -> None:
        self.procs[name].send_signal(sig)

    def close(self) -> None:
        for proc in reversed(list(self.procs.values())):
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(15)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait(10)
        for f in self._files:
            f.close()


class CuttableProxy:
    """A TCP proxy on 127.0.0.1 to ``target_port``; :meth:`cut` drops every connection and
    refuses new ones until :meth:`restore` (an agent's radio link lost)."""

    def __init__(self, target_port: int) -> None:
        self.target = target_port
        self.port = free_port(socket.SOCK_STREAM)
        self._lock = threading.Lock()
        self._conns: list[socket.socket] = []
        self._server: socket.socket | None = None
        self._stop = threading.Event()
        self._listen()

    def _listen(self) -> None:
        srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        srv.bind(("127.0.0.1", self.port))
        srv.listen(8)
        srv.settimeout(0.2)
        self._server = srv
        threading.Thread(target=self._accept, args=(srv,), daemon=True).start()

    def _accept(self, srv: socket.socket) -> None:
        while not self._stop.is_set() and self._server is srv:
            try:
                client, _ = srv.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            try:
                upstream = socket.create_connection(("127.0.0.1", self.target), timeout=5)
            except OSError:
                client.close()
                continue
            with self._lock:
                self._conns += [client, upstream]
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pipe, args=(a, b), daemon=True).start()

    def _pipe(self, a: socket.socket, b: socket.socket) -> None:
        try:
            while True:
                data = a.recv(65536)
                if not data:
                    break
                b.sendall(data)
        except OSError:
            pass
        finally:
            for s in (a, b):
                try:
                    s.close()
                except OSError:
                    pass

    def cut(self) -> None:
        with self._lock:
            srv, self._server = self._server, None
            conns, self._conns = self._conns, []
        if srv is not None:
            srv.close()
        for s in conns:
            try:
                s.shutdown(socket.SHUT_RDWR)
                s.close()
            except OSError:
                pass

    def restore(self) -> None:
        self._listen()

    def close(self) -> None:
        self._stop.set()
        self.cut()
