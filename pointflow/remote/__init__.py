"""Links between machines: a sensor host sends chunks to a pipeline elsewhere over ZeroMQ.

One module per concept: :mod:`.keys` (CURVE certificate files), :mod:`.options` (the link
options both ends share and the safe-default check), :mod:`.security` (CURVE, the ZAP
authenticator and the count of refused handshakes), :mod:`.codec` (compression and
position quantisation of wire frames), :mod:`.transit` (points lost in transit, from the
per-source link sequence) and :mod:`.sender` (the ``pointflow send`` stage). See
docs/remote.md.
"""
