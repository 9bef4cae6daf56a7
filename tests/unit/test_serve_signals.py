"""What a signal handler of `ripplecal serve` may do (issue 25, finding 1: a second signal arrived inside
the first one's EventBroker.close, which held a non-reentrant lock, and the main thread waited for itself
for good). The handler only records and sets flags; the broker closes with no lock, once. The processes
themselves, signalled twice, are tests/e2e/test_signals_e2e.py."""

from __future__ import annotations

import asyncio
import signal
import threading
import types

import uvicorn
from fastapi import FastAPI

from service.cli.server import ServiceServer
from service.runs.events import END, EventBroker


def _run_in_loop(broker: EventBroker, action) -> list:
    """One subscriber on a loop of its own; `action(broker)` run on another thread while it listens;
    the messages the subscriber got."""

    async def listen() -> list:
        _, queue = broker.subscribe()
        worker = threading.Thread(target=action, args=(broker,), daemon=True)  # a deadlock fails, never hangs
        worker.start()
        await asyncio.get_running_loop().run_in_executor(None, worker.join, 10)
        await asyncio.sleep(0.05)  # the offers made through call_soon_threadsafe run
        got = []
        while not queue.empty():
            got.append(queue.get_nowait())
        return got

    return asyncio.run(listen())


def test_close_takes_no_lock_a_thread_holding_the_brokers_lock_closes_it():
    def close_inside_the_lock(broker: EventBroker) -> None:
        with broker._lock:  # as a signal arriving inside subscribe/unsubscribe would find it
            broker.close()

    got = _run_in_loop(EventBroker(), close_inside_the_lock)
    assert got == [END]


def test_close_is_idempotent_the_stream_gets_one_end():
    def close_twice(broker: EventBroker) -> None:
        broker.close()
        broker.close()

    assert _run_in_loop(EventBroker(), close_twice) == [END]


def test_publish_reaches_subscribers_until_they_unsubscribe():
    broker = EventBroker()

    async def scenario() -> tuple[list, list]:
        token = broker.subscribe()
        broker.publish("job.state", {"id": 1})
        await asyncio.sleep(0.05)
        first = [token[1].get_nowait() for _ in range(token[1].qsize())]
        broker.unsubscribe(token)
        broker.publish("job.state", {"id": 2})
        await asyncio.sleep(0.05)
        return first, [token[1].get_nowait() for _ in range(token[1].qsize())]

    first, after = asyncio.run(scenario())
    assert first == [("job.state", '{"id": 1}')] and after == []


def _server() -> tuple[ServiceServer, types.SimpleNamespace]:
    service = types.SimpleNamespace(broker=EventBroker(), shutdown_reason="service shut down")
    # not served: its backstop thread starts with serve(), so nothing here can end this process
    return ServiceServer(uvicorn.Config(FastAPI()), service), service


def test_the_handler_records_the_first_signal_and_leaves_the_broker_to_the_loop():
    server, service = _server()
    handler = threading.Thread(target=server.handle_exit, args=(signal.SIGTERM, None), daemon=True)
    with service.broker._lock:  # held, as the main thread inside subscribe would hold it
        handler.start()
        handler.join(5)
        assert not handler.is_alive(), "the handler waits for the broker's lock"
    assert server.should_exit and not server.force_exit
    assert service.shutdown_reason == "service shut down (SIGTERM)"
    assert not service.broker.closed  # closed by the event loop (ServiceServer.shutdown), not the handler


def test_a_second_signal_forces_the_exit_sigterm_as_sigint():
    pairs = [(signal.SIGTERM, signal.SIGTERM), (signal.SIGINT, signal.SIGINT), (signal.SIGTERM, signal.SIGINT)]
    for first, second in pairs:
        server, service = _server()
        server.handle_exit(first, None)
        assert not server.force_exit
        server.handle_exit(second, None)
        assert server.force_exit, (first, second)  # uvicorn alone forces on a second SIGINT only
        assert service.shutdown_reason == f"service shut down ({signal.Signals(first).name})"
