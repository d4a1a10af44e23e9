"""A batch stopped while its cluster starts, or while its workers compute, says one line.

SIGTERM during the start of a cluster is held until the cluster can be closed (else its
half-started workers are left to dask's exit handler, which fails with a traceback), and the
workers of a stopped batch do not log their scheduler's going away.
"""

from __future__ import annotations

import logging
import os
import signal

import pytest

from plenopiv.batch.cluster import _HeartbeatOfAStoppedBatch, _sigterm_deferred
from plenopiv.cli import sigterm_as_interrupt
from plenopiv.errors import Terminated


def test_a_sigterm_while_a_cluster_starts_is_raised_once_it_can_be_closed():
    steps = []
    with sigterm_as_interrupt(), pytest.raises(Terminated):
        with _sigterm_deferred():
            os.kill(os.getpid(), signal.SIGTERM)
            steps.append("started")                      # not interrupted half way
            steps.append("registered for closing")
    assert steps == ["started", "registered for closing"]
    with sigterm_as_interrupt(), _sigterm_deferred():
        steps.append("no signal, nothing raised")


def test_the_workers_of_a_stopped_batch_do_not_log_the_lost_scheduler():
    keep = _HeartbeatOfAStoppedBatch().filter
    lost = logging.LogRecord("distributed.worker", logging.ERROR, "", 0,
                             "Failed to communicate with scheduler during heartbeat.", (), None)
    other = logging.LogRecord("distributed.worker", logging.ERROR, "", 0,
                              "Compute Failed", (), None)
    assert not keep(lost) and keep(other)
