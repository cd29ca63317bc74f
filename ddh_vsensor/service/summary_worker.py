"""The day summary's worker process (:mod:`.summary`): ``python -m
ddh_vsensor.service.summary_worker``, messages on stdin, answers on stdout, both pickled
(:func:`.summary.write_message`). Ends when its stdin closes (the daemon stopped, or died) or
on SIGTERM (systemd stopping what a killed daemon left), writing the day first; a terminal's
Ctrl-C is the daemon's to act on. Whenever it has written a day, it judges the machine's
health from the summaries (:mod:`ddh_vsensor.diagnosis.health`), writes the health file and
hands it to the daemon.
"""

from __future__ import annotations

import os
import signal
import sys
from pathlib import Path

from ddh_vsensor.service.summary import NICE, read_message, write_message


def main() -> int:
    from ddh_vsensor.diagnosis.day_summary import DaySummaries
    from ddh_vsensor.diagnosis.health import refresh
    try:        # never the daemon's real-time policy (systemd resets it on fork; a shell not)
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (OSError, AttributeError):
        pass
    try:
        os.nice(NICE)
    except OSError:
        pass
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _stop)
    inbox, outbox = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr           # nothing else on the answers' pipe
    start = read_message(inbox)
    if start is None:
        return 0
    _, cfg, machine, directory, save_interval_s, health_path = start
    days = DaySummaries(cfg, machine, Path(directory), lean=True, resume=True,
                        save_interval_s=save_interval_s)
    judged = -1                       # the day writes the health was last judged after

    def judge() -> None:
        """The health from the summaries, when a day was written since (and at start)."""
        nonlocal judged
        if days.writes == judged:
            return
        judged = days.writes
        try:
            doc, notes = refresh(cfg, days.machine, Path(directory), Path(health_path))
        except Exception as exc:       # noqa: BLE001 - the summaries go on without it
            days.notes.append(f"cannot judge the health ({type(exc).__name__}: {exc})")
        else:
            days.notes.extend(notes)
            write_message(outbox, ("health", doc))

    def answer(kind: str, text: str = "") -> None:
        judge()
        for note in days.notes:
            bad = "cannot" in note or "not gone on" in note or "left out" in note
            write_message(outbox, ("warning" if bad else "info", note))
        days.notes.clear()
        write_message(outbox, (kind, text))

    judge()
    try:
        while (message := read_message(inbox)) is not None:
            if message[0] == "close":
                break
            _, actuator, block = message
            try:
                days.feed(actuator, block)
            except Exception as exc:   # noqa: BLE001 - a failed stretch must not end the day
                write_message(outbox, ("warning", f"{actuator}: samples not summarised "
                                                  f"({type(exc).__name__}: {exc})"))
            answer("done")
    except _Stopped:
        pass
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    days.close()                      # asked to, or the daemon went: the day as it is
    try:
        answer("done")
    except OSError:
        pass                          # no daemon to answer
    return 0


class _Stopped(Exception):
    """SIGTERM: end every stretch, write the day, exit."""


def _stop(_signum: int, _frame: object) -> None:
    raise _Stopped


if __name__ == "__main__":
    sys.exit(main())
