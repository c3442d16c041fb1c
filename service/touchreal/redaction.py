"""Secrets out of whatever is shown: ``/v1/status``, hello, logs, metrics, error answers, banners.

:func:`redact` masks, anywhere in a text:

* the password of a URL's user info: ``nats://publisher:***@host:4222`` (the user name stays);
* a user info without a password, which NATS takes as a token: ``nats://***@host:4222``;
* the value of a secret-named query parameter: ``ws://host/v1/stream?token=***``;
* nkey seeds (``S`` + the key type + 56 base32 characters; their public keys stay).

It is applied to the text of a value where it is shown, so every place that shows a URL or an
error uses this one function.
"""

from __future__ import annotations

import re

MASK = "***"
#: scheme://USERINFO@ : the user info runs to the last '@' before the path, query, fragment or a space.
#: The scheme is at most 32 characters, so each start position is tried in bounded time (linear overall).
_USERINFO = re.compile(r"(?P<scheme>\b[A-Za-z][A-Za-z0-9+.-]{0,31}://)(?P<info>[^/\s?#]*)@")
_SECRET_PARAM = re.compile(r"(?P<key>[?&;](?:token|access_token|auth|password|passwd|pass|pwd|secret|key|api_key|apikey"
                           r"|jwt|sig|signature)=)[^&;#\s]*", re.IGNORECASE)
_NKEY_SEED = re.compile(r"\bS[A-Z][A-Z2-7]{56}\b")


def _userinfo(m: re.Match[str]) -> str:
    user, colon, _ = m["info"].partition(":")
    return f"{m['scheme']}{user}:{MASK}@" if colon else f"{m['scheme']}{MASK}@"


def redact(text: str) -> str:
    """``text`` with every password, token and nkey seed it contains replaced by ``***``."""
    text = _USERINFO.sub(_userinfo, text)
    text = _SECRET_PARAM.sub(lambda m: m["key"] + MASK, text)
    return _NKEY_SEED.sub(MASK, text)
