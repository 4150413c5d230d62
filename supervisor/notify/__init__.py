"""Notifications of alarms and test ends by e-mail and webhooks (issue 34,
docs/notifications.md, docs/adr/0049-notification-queue.md).

``Notifier(cfg.notifications, bench, clock, state_dir, db=…, alarms=…)``: its listeners
take the alarm model's and the step chains' events (a deque append on the scan's thread),
its task routes them (``Router``: filters, flood windows, quiet hours, escalations), queues
the messages in ``<state_dir>/notify.sqlite`` (``NotifyStore``, idempotency key per
message) and delivers them (``delivery``: SMTP in a thread, aiohttp), retried with backoff,
counted (``notify.*`` tags) and alarmed (``notify.failing``). Nothing here is imported by
the scan or the safety code: a notification never makes the scan wait.
"""

from supervisor.notify.delivery import (
    FORMATS,
    PAYLOAD_VERSION,
    DeliveryError,
    Sender,
    email_message,
    payload,
    sender_of,
    webhook_request,
)
from supervisor.notify.notifier import ALARM_FAILING, Notifier, send_test
from supervisor.notify.router import Notice, Outgoing, Router, message_key
from supervisor.notify.store import NOTIFY_NAME, NotifyStore, notify_path

__all__ = [
    "ALARM_FAILING",
    "FORMATS",
    "NOTIFY_NAME",
    "PAYLOAD_VERSION",
    "DeliveryError",
    "Notice",
    "Notifier",
    "NotifyStore",
    "Outgoing",
    "Router",
    "Sender",
    "email_message",
    "message_key",
    "notify_path",
    "payload",
    "send_test",
    "sender_of",
    "webhook_request",
]
