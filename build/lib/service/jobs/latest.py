"""A one-slot mailbox where the newest request wins: λ changes arrive in bursts while a
slider is dragged, and only the last one matters.

`submit` replaces whatever is still waiting and returns a ticket; one drain thread per
mailbox applies the newest value; `wait(ticket)` returns the result of the first application
at or after that ticket, so superseded requests get the version that holds the latest λ.
"""
from __future__ import annotations

import threading
from typing import Callable, Generic, TypeVar

T = TypeVar("T")
R = TypeVar("R")


class LatestWins(Generic[T, R]):
    def __init__(self, apply: Callable[[T], R], name: str = "latest-wins") -> None:
        self._apply = apply
        self._name = name
        self._cond = threading.Condition()
        self._pending: tuple[int, T] | None = None
        self._next_ticket = 0
        self._done_ticket = -1
        self._result: R | None = None
        self._failure: tuple[int, BaseException] | None = None  # (ticket, error) of the last failure
        self._draining = False

    def submit(self, value: T) -> int:
        with self._cond:
            ticket = self._next_ticket
            self._next_ticket += 1
            self._pending = (ticket, value)
            if not self._draining:
                self._draining = True
                threading.Thread(target=self._drain, name=self._name, daemon=True).start()
            return ticket

    def wait(self, ticket: int, timeout: float | None = None) -> R:
        """The result covering `ticket`; re-raises the error if that application failed."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._done_ticket >= ticket, timeout):
                raise TimeoutError(f"request {ticket} not applied within {timeout} s")
            if self._failure is not None and self._failure[0] >= ticket and self._failure[0] == self._done_ticket:
                raise self._failure[1]
            return self._result

    def _drain(self) -> None:
        while True:
            with self._cond:
                if self._pending is None:
                    self._draining = False
                    return
                ticket, value = self._pending
                self._pending = None
            try:
                result, failure = self._apply(value), None
            except BaseException as exc:  # handed to the waiters, who report it
                result, failure = None, exc
            with self._cond:
                self._done_ticket = ticket
                if failure is None:
                    self._result = result
                    self._failure = None
                else:
                    self._failure = (ticket, failure)
                self._cond.notify_all()
