"""What a Prefect API answers a client with or without its basic-auth secret (tests of the
servers typ starts, which ask for one)."""
from __future__ import annotations

import base64
import json
import urllib.error
import urllib.request


def api_status(api_url: str, auth: str | None) -> int:
    """HTTP status of a read of the API's flows (``POST /flows/filter``), sent with ``auth`` as
    basic auth, or with no credentials when it is None."""
    request = urllib.request.Request(f"{api_url}/flows/filter", data=b"{}", method="POST",
                                     headers={"Content-Type": "application/json"})
    if auth is not None:
        request.add_header("Authorization", "Basic " + base64.b64encode(auth.encode()).decode())
    try:
        with urllib.request.urlopen(request, timeout=30) as response:
            assert isinstance(json.load(response), list)
            return response.status
    except urllib.error.HTTPError as refused:
        return refused.code
