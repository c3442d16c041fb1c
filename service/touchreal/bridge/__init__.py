"""Live fan-out through NATS (docs/scale-out.md): the service publishes, stateless gateways serve.

- :mod:`.subjects`   subject names and message headers of one sensor on the broker
- :mod:`.upstream`   sans-I/O: a gateway's view of the published stream (gaps, publisher restarts)
                     and a published frame back into a hub :class:`~touchreal.server.runtime.Update`
- :mod:`.demand`     sans-I/O: the demand gateways forward to the publisher, bounded, merged with expiry
- :mod:`.auth`       credentials and TLS for the broker connection (publisher and gateways)
- :mod:`.publisher`  ``touchreal serve --publish``: the service's frames onto NATS (a hub subscriber)
- :mod:`.gateway`    ``touchreal gateway``: /v1/stream served from NATS through the same Hub and ws layer
- :mod:`.command`    the ``touchreal gateway`` command line
"""
