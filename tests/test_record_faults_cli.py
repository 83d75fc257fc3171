"""``whiztap record --faults FILE`` and ``--fault`` as a user types them: the
real command, the simulator, a client; and the one-line errors."""

from __future__ import annotations


import pytest

from whiztap.sniffer.sim.client import Client, ResponseTimeout
from whiztap.sniffer.sim.simulator import Simulator
from tests.cli_support import Ran, run_cli
from tests.record_support import LOCAL, RecordProcess, read_all

FAULTS_TOML = '''
[faults.flaky-answers]
spec = "drop dir:s2c kind:response ch:12 every:2"

[faults.big-value]
spec = 'replace:"cr1-13--999--0-ss1" dir:s2c kind:response ch:13 nth:1'
'''


@pytest.mark.slow
async def test_a_faults_file_and_a_fault_act_together_each_named_in_the_recording(tmp_path):
    faults = tmp_path / "faults.toml"
    faults.write_text(FAULTS_TOML)
    out = tmp_path / "r.mcap"
    async with Simulator(port=0, mode="vpn", seed=7) as sim:
        rec = await RecordProcess.start(sim.port, out, "--faults", str(faults), "--fault", "delay:20ms dir:s2c ch:14")
        async with await Client.connect(LOCAL, rec.port, timeout=0.5) as client:
            assert await client.sensor(13) == 999
            answers = []
            for _ in range(4):
                try:
                    answers.append(await client.sensor(12))
                except ResponseTimeout:
                    answers.append(None)
            assert [a is None for a in answers] == [False, True, False, True]
            assert 0 <= await client.sensor(14) <= 1024
        code, _, err = await rec.finish()
    assert code == 0, err
    causes = {m["action"]: m["cause"] for m in read_all(str(out))["/interventions"]}
    assert causes["drop"] == "fault flaky-answers: drop dir:s2c kind:response ch:12 every:2"
    assert causes["replace"].startswith("fault big-value: ")
    assert causes["delay"] == "fault fault-3: delay:20ms dir:s2c ch:14"


def _record(tmp_path, *args: str) -> Ran:
    return run_cli("record", "--listen", "127.0.0.1:0", "--upstream", "127.0.0.1:9", "-o", tmp_path / "r.mcap", *args)


def test_a_bad_faults_file_is_one_line_naming_the_file(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[faults.x]\nspec = "drop dri:s2c"\n')
    for args, needle in ((["--faults", str(bad)], "dri:s2c"), (["--faults", str(tmp_path / "none.toml")], "none.toml"),
                         (["--script", str(tmp_path / "none.py")], "none.py")):
        done = _record(tmp_path, *args)
        assert done.returncode == 2, done
        assert len(done.stderr.splitlines()) == 1 and needle in done.stderr and "Traceback" not in done.stderr
        assert not (tmp_path / "r.mcap").exists()


def test_the_control_api_on_a_taken_port_is_one_line(tmp_path):
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        done = _record(tmp_path, "--control", str(taken.getsockname()[1]))
    assert done.returncode == 2 and len(done.stderr.splitlines()) == 1 and "control API" in done.stderr
    assert list(tmp_path.iterdir()) == []  # no recording begun
