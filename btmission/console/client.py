"""A client of a running mission's operator console (what ``btmission task``, ``status`` and
``fleet`` use; a script may too). Standard library only: it runs where the viz extra is not
installed.

The URL is the one the run printed (``http://127.0.0.1:8470/?token=…``): the token may be in it,
or given apart (``token=``, the ``BTMISSION_TOKEN`` environment variable, a file).
"""

from __future__ import annotations

import json
import ssl
import urllib.error
import urllib.request
from dataclasses import dataclass
from typing import Any
from urllib.parse import parse_qs, quote, urlsplit, urlunsplit

from btmission.errors import BtmissionError

TIMEOUT_S = 15.0
"""How long a request may take (a command waits up to 5 s for the run's step)."""
MAX_ANSWER_BYTES = 16_000_000
"""The largest answer read (a status of 10,000 tasks is about 3 MB)."""


class ConsoleClientError(BtmissionError):
    """The console refused a request (``status``, its ``message``), or cannot be reached
    (``status`` 0)."""

    def __init__(self, message: str, status: int = 0, answer: Any = None) -> None:
        super().__init__(message)
        self.status = status
        self.answer = answer


def split_url(url: str) -> tuple[str, str | None]:
    """``(base URL ending in /, token in its query or None)``; :class:`ConsoleClientError` for
    what is not an http(s) URL."""
    parts = urlsplit(url.strip())
    if parts.scheme not in ("http", "https") or not parts.netloc:
        raise ConsoleClientError(
            f"'{url}' is not the console's URL (expected http://HOST:PORT/ as the run printed it)"
        )
    token = parse_qs(parts.query).get("token", [None])[0]
    path = parts.path.split("/api/", 1)[0]  # a route's URL pasted instead of the page's
    path = path if path.endswith("/") else path + "/"
    return urlunsplit((parts.scheme, parts.netloc, path, "", "")), token


@dataclass
class ConsoleClient:
    """Talks to the console at ``url`` with ``token`` (needed for commands)."""

    url: str
    token: str | None = None
    client: str = "cli"
    """Who the commands are logged as (``cli@<address>``)."""
    insecure: bool = False
    """Accept any TLS certificate (a self-signed one on a test rig)."""

    def __post_init__(self) -> None:
        base, in_url = split_url(self.url)
        self.url = base
        self.token = self.token or in_url

    # ---------------------------------------------------------------- requests
    def request(self, method: str, path: str, body: Any = None) -> Any:
        """The JSON answer of ``method path``; :class:`ConsoleClientError` for a refusal (its
        ``message``) or when nothing answers."""
        headers = {"Accept": "application/json", "X-Btmission-Client": self.client}
        if self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        data = None
        if body is not None:
            data = json.dumps(body).encode()
            headers["Content-Type"] = "application/json"
        req = urllib.request.Request(self.url + path, data=data, method=method, headers=headers)
        context = None
        if self.insecure and self.url.startswith("https:"):
            context = ssl._create_unverified_context()  # the user asked for it (--insecure)
        try:
            with urllib.request.urlopen(req, timeout=TIMEOUT_S, context=context) as resp:
                return _json(resp.read(MAX_ANSWER_BYTES + 1), self.url)
        except urllib.error.HTTPError as exc:
            answer = _json(exc.read(MAX_ANSWER_BYTES + 1), self.url, strict=False)
            message = answer.get("message") if isinstance(answer, dict) else None
            raise ConsoleClientError(
                str(message or f"{exc.code} {exc.reason}"), exc.code, answer
            ) from None
        except urllib.error.URLError as exc:
            reason = getattr(exc.reason, "strerror", None) or str(exc.reason)
            raise ConsoleClientError(
                f"cannot reach the console at {self.url}: {reason} (is the run still going, "
                "started with --console?)"
            ) from None
        except (TimeoutError, OSError) as exc:
            raise ConsoleClientError(f"no answer from {self.url}: {exc}") from None

    def info(self) -> dict[str, Any]:
        out: dict[str, Any] = self.request("GET", "api/info")
        return out

    def console(self) -> dict[str, Any]:
        """The task types, places, priority names and next task id (``/api/console``)."""
        out: dict[str, Any] = self.request("GET", "api/console")
        return out

    def status(self) -> dict[str, Any]:
        out: dict[str, Any] = self.request("GET", "api/status")
        return out

    def add_task(self, task: dict[str, Any]) -> dict[str, Any]:
        out: dict[str, Any] = self.request("POST", "api/tasks", task)
        return out

    def cancel_task(self, task: str) -> dict[str, Any]:
        out: dict[str, Any] = self.request("DELETE", f"api/tasks/{quote(task, safe='')}")
        return out

    def set_priority(self, task: str, priority: float | str) -> dict[str, Any]:
        path = f"api/tasks/{quote(task, safe='')}"
        out: dict[str, Any] = self.request("PATCH", path, {"priority": priority})
        return out

    def agent(self, agent: str, action: str, body: Any = None) -> dict[str, Any]:
        """``recall``, ``exclude``, ``include`` or ``link`` (``{"up": bool}``)."""
        path = f"api/agents/{quote(agent, safe='')}/{action}"
        out: dict[str, Any] = self.request("POST", path, body)
        return out

    def set_allocation(self, paused: bool) -> dict[str, Any]:
        out: dict[str, Any] = self.request("POST", "api/allocation", {"paused": paused})
        return out

    def stop(self, reason: str = "") -> dict[str, Any]:
        out: dict[str, Any] = self.request("POST", "api/stop", {"reason": reason})
        return out


def _json(raw: bytes, url: str, *, strict: bool = True) -> Any:
    if len(raw) > MAX_ANSWER_BYTES:
        raise ConsoleClientError(f"the answer from {url} is over {MAX_ANSWER_BYTES} bytes")
    try:
        return json.loads(raw or b"null")
    except ValueError:
        if not strict:
            return None
        raise ConsoleClientError(f"{url} did not answer JSON: is it a btmission console?") from None
