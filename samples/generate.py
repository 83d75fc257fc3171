"""Make the sample recordings in this folder (run by `make samples`).

Each sample is real traffic: the simulator (or, for the violations sample, a
scripted peer) behind whiztap's recording proxy, driven by the client library.
"""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path

from whiztap.analyzer.protocol.examples import SCENARIOS
from whiztap.sniffer.sim.client import Client, HandshakeError
from whiztap.sniffer.sim.dialogue import Dialogue
from whiztap.sniffer.record.record_run import Recording, RecordSettings
from whiztap.sniffer.sim.simulator import Simulator
from whiztap.sniffer.sim.tour import every_command

HERE = Path(__file__).parent
LOCAL = "127.0.0.1"
PASSWORD = "progwhiz"


async def recorded(upstream_port: int, path: Path, session, keep_secrets: bool = False) -> None:
    """Run ``session(proxy_port)`` (an async callable) through a recording proxy into ``path``."""
    path.unlink(missing_ok=True)
    recording = Recording(RecordSettings((LOCAL, 0), (LOCAL, upstream_port), str(path), quiet=True,
                                         keep_secrets=keep_secrets))
    await recording.start()
    try:
        await session(recording.proxy.port)
        await asyncio.sleep(0.2)  # let the last answers cross the proxy
    finally:
        await recording.stop()
    print(f"wrote {path.relative_to(HERE.parent)}")


async def clean_winsock() -> None:
    async with Simulator(mode="winsock", password=PASSWORD, seed=1) as sim:
        async def session(port: int) -> None:
            async with await Client.connect(LOCAL, port, password=PASSWORD) as client:
                await every_command(client)
                for _ in range(10):
                    await client.sensor(12)
                    await asyncio.sleep(0.05)
        await recorded(sim.port, HERE / "clean-winsock.mcap", session)


async def vpn() -> None:
    async with Simulator(mode="vpn", seed=2) as sim:
        async def session(port: int) -> None:
            async with await Client.connect(LOCAL, port) as client:
                await client.fetch_configuration()
                await client.normal_send(2, 2000)
                for i in range(20):
                    await client.sensor(12 + i % 4)
                    await client.servo_position(2)
                    await asyncio.sleep(0.05)
        await recorded(sim.port, HERE / "vpn.mcap", session)


async def failed_password() -> None:
    async with Simulator(mode="winsock", password=PASSWORD, seed=3) as sim:
        async def session(port: int) -> None:
            try:
                await Client.connect(LOCAL, port, password="not-the-password")
            except HandshakeError:
                return
            raise RuntimeError("the simulator accepted a wrong password")
        await recorded(sim.port, HERE / "failed-password.mcap", session)


async def violations() -> None:
    async with Dialogue() as peer:
        async def session(port: int) -> None:
            for steps in SCENARIOS.values():
                await peer.play(steps, (LOCAL, port))
        # --keep-secrets: the scenarios' passwords are made up; kept, the
        # report shows every scenario's bytes as they were sent
        await recorded(peer.port, HERE / "violations.mcap", session, keep_secrets=True)


async def main() -> None:
    for make in (clean_winsock, vpn, failed_password, violations):
        await make()


if __name__ == "__main__":
    try:
        asyncio.run(main())
    except KeyboardInterrupt:
        sys.exit("generate: interrupted")
