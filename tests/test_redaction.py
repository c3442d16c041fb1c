"""touchreal.redaction.redact, and how the NATS bridge names an authentication method given in a URL.
(End to end, through a real server, gateway and nats-server: tests/test_bridge_nats_auth.py.)"""

from __future__ import annotations

import secrets

import nkeys
import pytest

from touchreal.bridge.auth import NatsAuth, servers
from touchreal.redaction import redact


@pytest.mark.parametrize("text, shown", [
    ("nats://publisher:s3cret@nats:4222", "nats://publisher:***@nats:4222"),
    ("tls://tok3n@nats:4222", "tls://***@nats:4222"),  # a user info without a password is a token to NATS
    ("nats://u:p%40ss@h:4222,nats://v:w@k:4222", "nats://u:***@h:4222,nats://v:***@k:4222"),
    ("nats://u:p@ss@h:4222", "nats://u:***@h:4222"),  # an unescaped '@': up to the last one before the host
    ("error: cannot reach nats://u:pw@h/x?token=abc&b=1", "error: cannot reach nats://u:***@h/x?token=***&b=1"),
    ("ws://h:8765/v1/stream?Password=x#f", "ws://h:8765/v1/stream?Password=***#f"),
    ("nats://nats:4222 and ws://h/v1/stream?taxels=1", "nats://nats:4222 and ws://h/v1/stream?taxels=1"),  # no secret
    ("serial:socket://u:pw@10.0.0.2:7000", "serial:socket://u:***@10.0.0.2:7000"),
    ("user gateway at alice@example.org", "user gateway at alice@example.org"),  # not a URL: unchanged
])
def test_redact_masks_url_passwords_tokens_and_secret_query_parameters(text, shown):
    assert redact(text) == shown


def test_redact_masks_nkey_seeds_but_not_public_keys():
    seed = nkeys.encode_seed(secrets.token_bytes(32), nkeys.PREFIX_BYTE_USER).decode()
    public = nkeys.from_seed(bytearray(seed.encode())).public_key.decode()
    assert redact(f"seed {seed}, public key {public}") == f"seed ***, public key {public}"


def test_credentials_in_the_url_are_named_as_the_method_and_cannot_be_combined_with_flags():
    assert servers("u:p@h1:4222, nats://h2") == ["nats://u:p@h1:4222", "nats://h2"]  # as nats-py reads them
    none = NatsAuth()
    assert none.describe(servers("nats://publisher:pw@h:4222")) == "user publisher (in the URL)"
    assert none.describe(servers("tls://t0ken@h:4222")) == "token (in the URL) over TLS"
    assert none.describe(servers("h:4222")) == "anonymous"
    flags = NatsAuth(user="gateway", password="pw")
    assert flags.describe(servers("nats://h:4222")) == "user gateway"
    with pytest.raises(ValueError, match="one method") as exc:
        flags.check(servers("nats://publisher:pw2@h:4222"))
    assert "pw2" not in str(exc.value)


def test_redacting_hostile_text_takes_time_linear_in_its_length():
    """Texts shaped to make a backtracking pattern retry at every position (dot runs, scheme after
    scheme): 8x the length in well under 8x squared the time."""
    import time

    for unit in ("a.", "a://", "a://b:c", "x+"):
        t = []
        for n in (4096, 32768):
            text = unit * n
            t0 = time.perf_counter()
            redact(text)
            t.append(time.perf_counter() - t0)
        assert t[1] <= 20 * t[0] + 0.05, (unit, t)
