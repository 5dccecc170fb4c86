"""Links between machines: a sensor host sends chunks to a pipeline elsewhere, over ZeroMQ
or Zenoh (docs/remote.md).

One module per concept:

* both ends: :mod:`.options` (the link options both ends share, the safe-default check,
  the ``send:`` section), :mod:`.keys` (CURVE certificate files), :mod:`.security` (CURVE,
  the ZAP authenticator and the count of refused handshakes), :mod:`.transit` (points lost
  in transit, from the per-source link sequence); compression and quantisation of the
  frames are the wire format's (:mod:`pointflow.codec`);
* the sending host (``pointflow send``): :mod:`.process` (the sender stage, which picks
  the engine), :mod:`.sender` (the ZeroMQ engine's sender), :mod:`.zenoh_sender` (the
  Zenoh engine's);
* Zenoh: :mod:`.zenoh_options` (the ``zenoh:`` block, opening a session),
  :mod:`.router_process` (``pointflow router``, a supervised Zenoh router stage),
  :mod:`.zenoh_log` (refused TLS handshakes, read from the engine's log),
  :mod:`.tls` (``pointflow keys --tls``: a CA and host certificates).

The receiving end is an ordinary source: the ``zmq`` and ``zenoh`` transports
(pointflow/ingest/transports/).
"""
