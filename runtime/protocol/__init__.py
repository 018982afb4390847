"""The machine interface and the runtime<->server interface: Zenoh key expressions and messages.

Every message on the wire is one JSON document validated by a pydantic model from
:mod:`runtime.protocol.messages`; every key expression is built by :mod:`runtime.protocol.keys`.
See ``runtime/protocol/README.md`` for the table of keys, who publishes them and at what rate.
"""

from runtime.protocol import keys, messages

__all__ = ["keys", "messages"]
