"""One JSON request to a precond server, for the measurement scripts under scripts/ (which
talk to the API directly, below the Python client, to time or provoke exactly one exchange).

`call(base, method, path, body)` sends `body` as JSON and answers `(status, answer)`: the
parsed JSON answer, or None when there is none or it is not JSON. An HTTP error status is an
answer, not an exception; a server that cannot be reached raises `OSError`.
"""

import json
import urllib.error
import urllib.request
from typing import Any


def call(base: str, method: str, path: str, body: Any = None,
         timeout: float = 120) -> tuple[int, Any]:
    """One request, no retries: the status and the JSON answer (None when there is none)."""
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(base + path, data=data, method=method)
    if data is not None:
        req.add_header("Content-Type", "application/json")
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.status, _parse(r.read())
    except urllib.error.HTTPError as e:
        return e.code, _parse(e.read())


def _parse(text: bytes) -> Any:
    try:
        return json.loads(text) if text else None
    except ValueError:
        return None
