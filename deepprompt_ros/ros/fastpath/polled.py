"""Entities that no executor waits on: the thread that owns them takes their messages or requests
itself, when it is ready for them.

At control rate an executor callback per message costs most of a CPU core in Python (a wait set
rebuilt over the node's entities, a hand-over to a callback thread). A subscription or service
created in a :class:`NotExecuted` callback group stays on its node (``ros2 node info`` lists it,
names and remappings resolve as for any other entity), but rclpy's executors leave it out of
their wait sets: they only wait on entities whose group ``can_execute`` them. Its owner then takes
messages with :func:`take_newest` / :func:`take_all` (rclpy's private subscription handle) or
serves requests with :class:`~deepprompt_ros.ros.fastpath.service_thread.ServiceThread`.
"""
from __future__ import annotations

from typing import Any, Iterator

from rclpy.callback_groups import CallbackGroup

__all__ = ["NotExecuted", "take_newest", "take_all"]


class NotExecuted(CallbackGroup):
    """A callback group whose entities no executor waits on or runs."""

    def can_execute(self, entity) -> bool:
        return False

    def beginning_execution(self, entity) -> bool:
        return False

    def ending_execution(self, entity) -> None:
        pass


def take_all(subscription, raw: bool | None = None) -> Iterator[tuple[Any, dict]]:
    """Every message waiting in ``subscription``'s queue, oldest first, as (message, message info);
    ``raw``: serialized bytes instead of a message (default: as the subscription was created)."""
    raw = subscription.raw if raw is None else raw
    with subscription.handle:
        while (taken := subscription.handle.take_message(subscription.msg_type, raw)) is not None:
            yield taken


def take_newest(subscription, raw: bool | None = None):
    """The newest message waiting in ``subscription``'s queue (the older ones are dropped), or None."""
    msg = None
    for msg, _ in take_all(subscription, raw):
        pass
    return msg
