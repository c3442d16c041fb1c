"""TouchReal client: the /v1/stream wire protocol, REST helpers and the decoder features shared
with the service. Light on purpose (numpy, websockets, httpx): a robot computer needs nothing else.
"""

__version__ = "0.1.0"
