"""A TCP relay that holds every byte for a fixed time each way: latency between hosts in the tests and
the bench, on a kernel without ``netem`` (tests/network.py). Run it inside the namespace of the host
whose links should be slow, listening on that host's loopback, forwarding to the peer's address:

    ip netns exec NS python -m tests.relay --listen 127.0.0.1:7000 --to 10.1.2.1:61002 --delay-ms 25

A role in ``NS`` then calls ``127.0.0.1:7000`` and every exchange takes ``2 * delay`` longer (25 ms each
way: a 50 ms round trip). Bytes keep their order; each direction of each connection is a queue of
``(due, bytes)``; a connection closed on one side is closed on the other once its bytes are through.
It prints ``relay listening on HOST:PORT`` once it accepts connections.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import sys


async def _pipe(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, delay_s: float) -> None:
    loop = asyncio.get_running_loop()
    held: asyncio.Queue[tuple[float, bytes]] = asyncio.Queue()

    async def take() -> None:
        while True:
            try:
                data = await reader.read(1 << 16)
            except ConnectionError:
                data = b""
            await held.put((loop.time() + delay_s, data))
            if not data:
                return

    async def give() -> None:
        while True:
            due, data = await held.get()
            wait = due - loop.time()
            if wait > 0:
                await asyncio.sleep(wait)
            if not data:
                with contextlib.suppress(OSError):
                    writer.write_eof()
                return
            writer.write(data)
            try:
                await writer.drain()
            except ConnectionError:
                return

    await asyncio.gather(take(), give())


async def _serve(listen: tuple[str, int], to: tuple[str, int], delay_s: float) -> None:
    async def connection(client_reader: asyncio.StreamReader, client_writer: asyncio.StreamWriter) -> None:
        try:
            peer_reader, peer_writer = await asyncio.open_connection(*to)
        except OSError:
            client_writer.close()  # the peer is down: so is this connection, as a direct one would be
            return
        try:
            await asyncio.gather(_pipe(client_reader, peer_writer, delay_s), _pipe(peer_reader, client_writer, delay_s))
        finally:
            for w in (client_writer, peer_writer):
                w.close()

    server = await asyncio.start_server(connection, *listen)
    print(f"relay listening on {listen[0]}:{listen[1]}", flush=True)
    async with server:
        await server.serve_forever()


def _address(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    return host, int(port)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--listen", type=_address, required=True, help="HOST:PORT to accept connections on")
    parser.add_argument("--to", type=_address, required=True, help="HOST:PORT to forward them to")
    parser.add_argument("--delay-ms", type=float, required=True, help="how long each byte is held, each way")
    args = parser.parse_args(argv)
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(_serve(args.listen, args.to, args.delay_ms / 1000.0))


if __name__ == "__main__":
    sys.exit(main())
