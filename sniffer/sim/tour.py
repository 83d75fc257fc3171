"""A client session that uses every command of the spec once, cleanly.

The sample recordings and the demo both start from it, so the two show the
same protocol tour and add only what is theirs (more polling, deliberate
violations).
"""

from __future__ import annotations

import asyncio

from whiztap.analyzer.protocol import messages as m
from whiztap.sniffer.sim.client import Client

SPEC_EXAMPLE_ENTRIES = tuple(m.SetConfigEntry(12, port, 0) for port in range(6))  # checksum 72


async def every_command(client: Client) -> None:
    """Configuration, sensors, a servo move watched as it travels, switches,
    scripts, the spec's Set Configuration example and a camera image."""
    await client.fetch_configuration()
    for channel in (12, 13):
        await client.sensor(channel)
    await client.normal_send(0, 1500)
    for _ in range(5):
        await client.servo_position(0)
        await asyncio.sleep(0.1)
    await client.activate_switch(6)
    await client.deactivate_switch(6)
    await client.play_internal_script(120)
    await client.stop_internal_script()
    await client.play_external_script(272)
    await client.stop_external_script()
    await client.set_configuration(SPEC_EXAMPLE_ENTRIES)
    await client.fetch_camera_image()
