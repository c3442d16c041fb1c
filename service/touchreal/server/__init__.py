"""The networked service (``touchreal serve``): acquisition + encoding off the event loop, one
fan-out hub, the ``/v1/stream`` WebSocket and the ``/v1`` REST surface (docs/stream-protocol.md,
docs/service.md).

- :mod:`.settings`   service settings (flags, ``TOUCHREAL_*`` environment) and the PATCHable config
- :mod:`.sources`    ``--source`` specs -> live sources (sim, replay, serial)
- :mod:`.params_store` parameter sets: active, history, persisted in the state directory
- :mod:`.demand`     what the subscribers need -> what the pipeline computes
- :mod:`.runtime`    the acquisition + encoding thread
- :mod:`.hub`        fan-out: frames rendered once per update, bounded queue per subscriber
- :mod:`.service`    the one object the routers call
- :mod:`.ws`, :mod:`.rest`, :mod:`.metrics`, :mod:`.app`   thin FastAPI layers
"""
