"""TouchReal client: the /v1/stream wire protocol, the stream and REST clients (async and blocking)
and the decoder features shared with the service. Light on purpose (numpy, websockets, httpx): a
robot computer needs nothing else (onnxruntime, extra ``onnx``, to run decoders locally).

>>> from touchreal_client import Client, Subscription
>>> with Client("http://127.0.0.1:8765") as tr, tr.stream(Subscription(classes=["SA1", "RA"])) as s:
...     for frame in s.spikes():
...         print(frame.t_us, frame.taxel, frame.cls)
"""

from .backoff import Backoff
from .client import AsyncClient, Client, Stream
from .clock import ClockMap, ClockPoint
from .errors import (AuthError, NotFound, ParamsRejected, RequestError, ServiceUnavailable, StreamClosed, StreamError,
                     TouchRealError)
from .protocol import CLASSES, ChannelsFrame, DecodedFrame, Header, Region, SpikesFrame, Subscription
from .rest import AsyncRest
from .stats import Latency, LatencyEstimator, LatencySummary, StreamStats
from .stream import AsyncStream, DecodedOutput

__version__ = "0.1.0"
__all__ = [
    "AsyncClient", "AsyncRest", "AsyncStream", "AuthError", "Backoff", "CLASSES", "ChannelsFrame", "Client",
    "ClockMap", "ClockPoint", "DecodedFrame", "DecodedOutput", "Header", "Latency", "LatencyEstimator", "LatencySummary", "NotFound",
    "ParamsRejected", "Region", "RequestError", "ServiceUnavailable", "SpikesFrame", "Stream", "StreamClosed", "StreamError",
    "StreamStats", "Subscription", "TouchRealError",
]
