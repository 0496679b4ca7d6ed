"""The AMQP 1.0 sender of CFX messages (python-qpid-proton's blocking API, run in one thread).

Why blocking, in a thread of its own: one message at a time, each waited for until the broker
settles it, is exactly what the outbox needs (an entry is marked delivered only after the broker
ACCEPTED it; the next one waits). proton objects are not thread-safe, so every call runs on the
same single worker thread, never on the daemon's event loop.

The message is what the CFX SDK sends (AmqpUtilities.cs): the envelope as UTF-8 JSON in a data
section, content-type application/json; charset="utf-8", message-id = UniqueID, creation-time =
TimeStamp, reply-to = Source, subject = MessageName (or <handle>.<MessageName>: a topic exchange's
routing key), application properties cfx-topic / cfx-message / cfx-handle / cfx-target, and the
durable header (the broker keeps it on disk). The link's target is durable too, so a RabbitMQ
"/queue/NAME" it declares survives a broker restart.
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime

from proton import Delivery, Message, Terminus
from proton.reactor import LinkOption
from proton.utils import BlockingConnection, BlockingSender

from station.cfx.messages import Envelope

log = logging.getLogger("station.cfx")

CONTENT_TYPE = 'application/json; charset="utf-8"'


class CfxSendError(Exception):
    """The broker did not accept a message (unreachable, refused, timed out, not ACCEPTED)."""


class _DurableTarget(LinkOption):
    """A durable target terminus that never expires (RabbitMQ declares /queue/NAME durable)."""

    def apply(self, link: object) -> None:
        target = getattr(link, "target")
        target.durability = Terminus.DELIVERIES
        target.expiry_policy = Terminus.EXPIRE_NEVER


def redact(url: str) -> str:
    """The broker URL without its credentials (for logs and errors)."""
    return re.sub(r"//[^/@]*@", "//***@", url)


def encode(envelope: Envelope) -> bytes:
    """The envelope as UTF-8 JSON (the bytes on the wire; non-ASCII kept as UTF-8)."""
    return json.dumps(envelope, ensure_ascii=False, separators=(",", ":")).encode("utf-8")


def to_message(envelope: Envelope, subject_mode: str = "message_name") -> Message:
    """The AMQP message of one envelope (module doc)."""
    name, source = envelope["MessageName"], envelope["Source"]
    msg = Message(body=encode(envelope), inferred=True, durable=True)
    msg.id = envelope["UniqueID"]
    msg.subject = f"{source}.{name}" if subject_mode == "handle.message_name" else name
    msg.content_type = CONTENT_TYPE
    msg.reply_to = source
    msg.creation_time = datetime.fromisoformat(envelope["TimeStamp"]).timestamp()
    app_properties: dict[str, str | None] = {"cfx-topic": name.rsplit(".", 1)[0], "cfx-message": name,
                                             "cfx-handle": source, "cfx-target": envelope["Target"]}
    setattr(msg, "properties", app_properties)  # proton annotates the setter's value as None
    return msg


class AmqpSender:
    """One connection and sender link to the broker, opened on first use and again after a failure.
    Every method runs on this object's own single thread (await them from the event loop)."""

    def __init__(self, url: str, address: str, *, timeout_s: float = 10.0, subject_mode: str = "message_name",
                 container_id: str | None = None) -> None:
        self.url = url
        self.address = address
        self.timeout_s = timeout_s
        self.subject_mode = subject_mode
        self.container_id = container_id
        self._conn: BlockingConnection | None = None
        self._sender: BlockingSender | None = None
        self._thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix="cfx-amqp")

    async def send(self, envelope: Envelope) -> None:
        """Send one message and wait for the broker's ACCEPTED; CfxSendError otherwise."""
        await asyncio.get_running_loop().run_in_executor(self._thread, self._send, envelope)

    async def close(self) -> None:
        await asyncio.get_running_loop().run_in_executor(self._thread, self._drop)
        self._thread.shutdown(wait=False)

    def _open(self) -> BlockingSender:
        if self._sender is None:
            self._conn = BlockingConnection(self.url, timeout=self.timeout_s, container_id=self.container_id)
            self._sender = self._conn.create_sender(self.address, options=_DurableTarget())
        return self._sender

    def _send(self, envelope: Envelope) -> None:
        try:
            delivery = self._open().send(to_message(envelope, self.subject_mode), timeout=self.timeout_s)
        except Exception as exc:  # noqa: BLE001 - any failure of the link is one failed delivery
            self._drop()
            text = redact(f"{type(exc).__name__}: {exc}".strip())
            raise CfxSendError(f"{redact(self.url)} {self.address}: {text}") from None
        if delivery.remote_state != Delivery.ACCEPTED:
            self._drop()
            raise CfxSendError(f"{redact(self.url)} {self.address}: not accepted (disposition {delivery.remote_state})")

    def _drop(self) -> None:
        conn, self._conn, self._sender = self._conn, None, None
        if conn is not None:
            try:
                conn.close()
            except Exception as exc:  # noqa: BLE001 - a dead connection may not close cleanly
                log.debug("CFX: closing the AMQP connection: %s", exc)


__all__ = ["AmqpSender", "CfxSendError", "CONTENT_TYPE", "to_message", "encode", "redact"]
