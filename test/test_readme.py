"""The README's "Your own bag in 5 minutes" runs as written (issue 25: the own-bag commands run in a test).

Every command of the section is taken from the README itself, not copied here: the
simulated robot bag of step 1 (clouds in the lidar frame, /tf, /tf_static), ``inspect``,
offline ``replay`` and ``plot``, then the node and publish mode in two processes, with the
placeholders (BAG, /your/points, output/...) replaced by this test's files. The
node must receive and map every cloud, and log the summary line the README shows.
"""

from __future__ import annotations

import os
import re
import shlex
import signal
import subprocess
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SECTION = '## Your own bag in 5 minutes'


def section() -> str:
    text = (REPO / 'README.md').read_text()
    start = text.index(SECTION)
    end = text.index('\n## ', start + len(SECTION))
    return text[start:end]


def code_blocks(text: str) -> list[list[str]]:
    """The commands of each ```sh block, one per line, as written."""
    blocks = re.findall(r'```sh\n(.*?)```', text, flags=re.S)
    return [[line.strip() for line in block.strip().splitlines() if line.strip()] for block in blocks]


def simulate_command(text: str) -> str:
    """Step 1's inline command that records a robot bag."""
    flat = ' '.join(text.split())
    match = re.search(r'`(\.venv/bin/uncertain-facade-map simulate [^`]*)`', flat)
    assert match, 'step 1 names no simulate command'
    return match.group(1)


def concrete(command: str, work: Path, bag: Path) -> list[str]:
    """A README command with its placeholders replaced, as an argument list."""
    command = re.sub(r'\s*\[[^\]]*\]', '', command)  # optional arguments
    command = command.replace('/your/points', '/points').replace('output/', f'{work}/')
    args = shlex.split(command)
    out = []
    for arg in args:
        if arg == 'BAG':
            arg = str(bag)
        out.append(str(REPO / arg) if arg.startswith('.venv/') else arg)
    return out


def test_the_section_has_the_commands_a_user_needs():
    blocks = code_blocks(section())
    assert [b[0].split()[1] for b in blocks if not b[0].startswith('export')] == ['inspect', 'replay']
    assert any('facade_mapper --ros-args' in line for b in blocks for line in b)
    assert any('--mode publish' in line for b in blocks for line in b)
    assert sum(1 for b in blocks for line in b if line.startswith('export FASTRTPS_DEFAULT_PROFILES_FILE')) == 2


@pytest.mark.ros
def test_own_bag_commands_run_as_written(tmp_path):
    pytest.importorskip('rclpy')
    pytest.importorskip('tf2_msgs.msg')
    text = section()
    work = tmp_path
    # Step 1: a bag as a robot records it.
    simulate = concrete(simulate_command(text), work, work)
    simulate[simulate.index('--out') + 1] = str(work / 'robot')
    done = subprocess.run(simulate + ['--quiet'], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    bag = work / 'robot' / 'campaign0_mcap'
    blocks = code_blocks(text)
    offline = [line for block in blocks[:2] for line in block]
    live = [line for block in blocks[2:] for line in block]
    # Steps 2 and 3: inspect, replay, plot.
    outputs = []
    for line in offline:
        done = subprocess.run(concrete(line, work, bag), cwd=REPO, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, f'{line}\n{done.stdout}\n{done.stderr}'
        outputs.append(done.stdout)
    assert 'placed   100 of 100 clouds can be put into "map"' in outputs[0]
    assert 'mapped   2 buildings' in outputs[1] and (work / 'my_map.npz').is_file()
    assert (work / 'figures' / 'overview.png').is_file()
    # Step 4: the node in one process, publish mode in another, both with the DDS profile.
    exports = {}
    commands = []
    for line in live:
        if line.startswith('export '):
            name, value = line[len('export '):].split('=', 1)
            exports[name] = value.replace('$PWD', str(REPO))
        else:
            commands.append(line)
    node_line, publish_line = commands
    env = dict(os.environ, ROS_DOMAIN_ID=str(150 + (os.getpid() + 11) % 50), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               **exports)
    assert Path(env['FASTRTPS_DEFAULT_PROFILES_FILE']).is_file()
    log = work / 'node.log'
    with open(log, 'wb') as sink:
        node = subprocess.Popen(concrete(node_line, work, bag), cwd=REPO, env=env, stdout=sink, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while 'façades' not in log.read_text():
            assert node.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.2)
        done = subprocess.run(concrete(publish_line, work, bag) + ['--quiet'], cwd=REPO, env=env, capture_output=True,
                              text=True, timeout=300)
        assert done.returncode == 0, done.stderr
        assert 'the node received 100 of the 100 clouds published' in done.stdout, done.stdout
        deadline = time.monotonic() + 30
        while not re.search(r'last 5 s: .*map: [1-9]', log.read_text()):  # the summary after the idle flush
            assert time.monotonic() < deadline, log.read_text()
            time.sleep(0.5)
    finally:
        node.send_signal(signal.SIGINT)
        try:
            node.wait(20)
        except subprocess.TimeoutExpired:
            node.kill()
    written = log.read_text()
    print(written)
    assert 'rejected' not in written.replace('0 rejected', '')
    # The README's example summary line has the form the node logs.
    example = re.search(r'\[INFO\] \[facade_mapper\]: (last 5 s: .*)', text).group(1)
    shape = re.sub(r'[\d,]+', r'[\\d,]+', re.escape(example))
    assert re.search(shape.replace(r'last\ [\d,]+\ s', r'last\ 5\ s'), written), (example, written)
