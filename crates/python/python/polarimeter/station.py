"""A client of a polarimeter station (``polarimeter station serve``; docs/STATION.md), on the
standard library only: the queue, run control, the history, health and the event stream.

>>> st = Station("http://127.0.0.1:8750", key_file="station.key")
>>> (item,) = st.submit("examples/plans/capture.toml")
>>> st.wait([item])[0]["exit"]
'done'

Errors the station answers are raised as :class:`StationError` with the HTTP status, the
station's message and the request's field at fault.
"""

from __future__ import annotations

import json
import os
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

__all__ = ["Station", "StationError"]


class StationError(Exception):
    """A request the station refused (or could not be made).

    ``status`` is the HTTP status (0: the station could not be reached), ``field`` the
    request's field at fault, if the station named one."""

    def __init__(self, status: int, message: str, field: str | None = None):
        super().__init__(f"{status}: {message}" + (f" (field: {field})" if field else ""))
        self.status = status
        self.message = message
        self.field = field


class Station:
    """The station at ``url``, with an API key (``key``, or the first line of ``key_file``:
    what ``polarimeter station key create --key-out FILE`` writes)."""

    def __init__(self, url: str = "http://127.0.0.1:8750", *, key: str | None = None,
                 key_file: str | os.PathLike | None = None, timeout_s: float = 60.0):
        if not url.startswith(("http://", "https://")):
            raise ValueError(f"url {url!r}: write the station's address as http://HOST:PORT")
        if key is not None and key_file is not None:
            raise ValueError("give key or key_file, not both")
        if key_file is not None:
            lines = Path(key_file).read_text().splitlines()
            key = lines[0].strip() if lines else ""
            if not key:
                raise ValueError(f"key_file {key_file}: the file is empty")
        self.url = url.rstrip("/")
        self._key = key
        self.timeout_s = timeout_s

    def __repr__(self) -> str:
        return f"Station({self.url!r})"

    def _request(self, method: str, path: str, body: Any = None, *,
                 stream: bool = False, headers: dict[str, str] | None = None):
        data = None if body is None else json.dumps(body).encode()
        h = {"Accept": "application/json", **(headers or {})}
        if data is not None:
            h["Content-Type"] = "application/json"
        if self._key:
            h["Authorization"] = f"Bearer {self._key}"
        req = urllib.request.Request(self.url + path, data=data, method=method, headers=h)
        try:
            resp = urllib.request.urlopen(req, timeout=None if stream else self.timeout_s)
        except urllib.error.HTTPError as e:
            try:
                err = json.loads(e.read() or b"{}")
            except ValueError:
                err = {}
            if path == "/healthz" and e.code == 503:
                return err
            raise StationError(e.code, err.get("error") or e.reason, err.get("field") or None) from None
        except OSError as e:
            raise StationError(0, f"cannot reach the station at {self.url}: {e}") from None
        if stream:
            return resp
        with resp:
            return json.loads(resp.read() or b"null")

    # Reading.
    def health(self) -> dict:
        """``/healthz`` (no key needed): ``ok``, ``devices``, ``disk``, ``clock``, ``queue``,
        ``last_error``."""
        return self._request("GET", "/healthz")

    def status(self) -> dict:
        """The queue in brief, the current item and its progress, the next start."""
        return self._request("GET", "/api/v1/status")

    def queue(self) -> list[dict]:
        """The queued items in order, each with its ``next_start``."""
        return self._request("GET", "/api/v1/queue")["items"]

    def history(self, limit: int | None = None) -> list[dict]:
        """Items that left the station (oldest first), with ``exit`` and ``run_dir``."""
        q = "" if limit is None else f"?limit={int(limit)}"
        return self._request("GET", "/api/v1/history" + q)["items"]

    # The queue.
    @staticmethod
    def _item(plan: str | os.PathLike, priority: int, schedule: dict | None) -> dict:
        p = Path(plan) if not (isinstance(plan, str) and "\n" in plan) else None
        if p is not None and p.is_file():
            text, fmt = p.read_text(), "yaml" if p.suffix in (".yaml", ".yml") else "toml"
        elif p is not None and not isinstance(plan, str):
            raise FileNotFoundError(plan)
        else:
            text, fmt = str(plan), "toml"
        item: dict[str, Any] = {"plan": text, "format": fmt, "priority": int(priority)}
        if schedule is not None:
            item["schedule"] = schedule
        return item

    def submit(self, *plans: str | os.PathLike, priority: int = 0,
               schedule: dict | None = None) -> list[int]:
        """Queues plan files (or plan texts) as one batch, all or nothing; their ids."""
        items = [self._item(p, priority, schedule) for p in plans]
        return self._request("POST", "/api/v1/queue", {"items": items})["ids"]

    def validate(self, *plans: str | os.PathLike, schedule: dict | None = None) -> list[dict]:
        """Each plan's forecast as the station would queue it; queues nothing."""
        items = [self._item(p, 0, schedule) for p in plans]
        return self._request("POST", "/api/v1/queue/validate", {"items": items})["items"]

    def remove(self, item_id: int) -> None:
        """Removes a queued item (or the paused current one, which leaves as stopped)."""
        self._request("DELETE", f"/api/v1/queue/{int(item_id)}")

    def move(self, item_id: int, position: int) -> None:
        """Moves a queued item to ``position`` (0: next)."""
        self._request("POST", f"/api/v1/queue/{int(item_id)}/move", {"position": int(position)})

    def clear(self) -> None:
        """Removes this key's queued items (an admin key's: all)."""
        self._request("DELETE", "/api/v1/queue")

    def start(self) -> None:
        """Starts taking items."""
        self._request("POST", "/api/v1/queue/start", {})

    def stop(self) -> None:
        """Takes no new item after the current one."""
        self._request("POST", "/api/v1/queue/stop", {})

    # The current item.
    def pause(self) -> None:
        """Pauses the running item at its next set boundary."""
        self._request("POST", "/api/v1/run/pause", {})

    def resume(self) -> None:
        """Resumes the paused item."""
        self._request("POST", "/api/v1/run/resume", {})

    def abort(self) -> None:
        """Aborts the current item (what was acquired stays)."""
        self._request("POST", "/api/v1/run/abort", {})

    def wait(self, ids: list[int], timeout_s: float | None = None,
             poll_s: float = 0.5) -> list[dict]:
        """Waits until every item of ``ids`` has left the station; their history entries, in
        the order of ``ids``. ``TimeoutError`` after ``timeout_s``."""
        want = [int(i) for i in ids]
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            found = {e["item"]["id"]: e for e in self.history() if e["item"]["id"] in want}
            if len(found) == len(set(want)):
                return [found[i] for i in want]
            q = self._request("GET", "/api/v1/queue")
            here = {i["id"] for i in q["items"]}
            if q.get("current"):
                here.add(q["current"]["item"]["id"])
            later = {e["item"]["id"] for e in self.history()}
            gone = [i for i in want if i not in here and i not in later]
            if gone:
                raise StationError(404, f"items {gone} left the queue without running (removed)")
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"items {sorted(set(want) - set(found))} still at the station")
            time.sleep(poll_s)

    def events(self, last_event_id: int | None = None) -> Iterator[dict]:
        """The event stream: dicts with ``id`` (the change id), ``kind``, ``time`` and
        ``data``, starting with ``hello``; ``last_event_id`` replays what was missed."""
        headers = {"Accept": "text/event-stream"}
        if last_event_id is not None:
            headers["Last-Event-ID"] = str(int(last_event_id))
        resp = self._request("GET", "/api/v1/events", stream=True, headers=headers)
        with resp:
            for raw in resp:
                line = raw.decode("utf-8").rstrip("\r\n")
                if line.startswith("data:"):
                    yield json.loads(line[5:].strip())
