"""The fleet store: one directory of Parquet files, queried with DuckDB.

    DIR/logs/<log_id>/{meta,samples,events,holds}.parquet   one ingested log
    DIR/logs/<log_id>/{meta,evidence,context}.parquet       one ingested day summary
    DIR/rejected/<log_id>.json                               a file that could not be read
    DIR/fits/<machine>.parquet                               the per-machine analysis

``log_id`` is a hash of the file's bytes, so ingesting a file twice (under any name) finds it
present. A file's tables are written into a temporary directory and renamed into ``logs/``
in one step: after a crash it is either complete or absent (the temporary directory is
removed on the next run), so ingestion resumes where it stopped. ``meta.kind`` says which
it is ("log", "summary"; none in stores from before summaries: logs).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import duckdb
import pyarrow as pa
import pyarrow.parquet as pq

from ddh_vsensor.atomic import output_dir
from ddh_vsensor.errors import UserError

TABLES = ("meta", "samples", "events", "holds", "evidence", "context")
# The samples are read back whole, log by log: no dictionaries or statistics to build
# (a third less CPU per log, and half the bytes once zstd has them)
_PLAIN = {"use_dictionary": False, "write_statistics": False}


def log_id_of(data: bytes) -> str:
    return hashlib.sha1(data).hexdigest()[:20]


def _sync_file_system(directory: Path) -> None:
    """Flush every file written on ``directory``'s file system (Linux ``syncfs``: one call
    for a batch of logs instead of an fsync per file; ``sync`` elsewhere)."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        if _LIBC is None or _LIBC.syncfs(fd) != 0:
            os.sync()
    finally:
        os.close(fd)


def _libc():
    import ctypes
    import ctypes.util
    try:
        lib = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        lib.syncfs
    except (OSError, AttributeError):
        return None
    return lib


_LIBC = _libc()


class Store:
    def __init__(self, root: str | Path, create: bool = False) -> None:
        self.root = Path(root)
        if create:
            output_dir(self.root, "fleet store")
            try:
                for sub in ("logs", "rejected", "fits", "tmp"):
                    (self.root / sub).mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise UserError(f"--store {root}: cannot create: {exc.strerror or exc}") \
                    from None
        elif not (self.root / "logs").is_dir():
            raise UserError(f"--store {root}: not a fleet store (no logs/ inside); run "
                            "'ddh-vsensor fleet ingest' first")

    def has(self, log_id: str) -> bool:
        return (self.root / "logs" / log_id).is_dir() or \
            (self.root / "rejected" / f"{log_id}.json").is_file()

    def clean_partial(self) -> int:
        """Remove what a crashed ingestion left half written; returns how many."""
        tmp = self.root / "tmp"
        gone = 0
        for p in tmp.iterdir() if tmp.is_dir() else ():
            shutil.rmtree(p, ignore_errors=True)
            gone += 1
        return gone

    def put_log(self, log_id: str, tables: dict[str, pa.Table]) -> None:
        """All tables of one log, atomically (see :meth:`put_logs`)."""
        self.put_logs([(log_id, tables)])

    def put_logs(self, logs: list[tuple[str, dict[str, pa.Table]]]) -> None:
        """All tables of several logs, each log atomically: written into a temporary
        directory, the file system synced once for all of them, then each renamed into
        logs/ (a log is complete or absent after a crash, even of the machine)."""
        staged = []
        for log_id, tables in logs:
            final = self.root / "logs" / log_id
            if final.is_dir():
                continue
            tmp = self.root / "tmp" / f"{log_id}.{os.getpid()}"
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir(parents=True)
            for name, table in tables.items():
                pq.write_table(table, tmp / f"{name}.parquet", compression="zstd",
                               **_PLAIN if name == "samples" else {})
            staged.append((tmp, final))
        if not staged:
            return
        _sync_file_system(self.root / "tmp")
        for tmp, final in staged:
            try:
                os.rename(tmp, final)
            except OSError:                  # another worker put the same log first
                shutil.rmtree(tmp, ignore_errors=True)

    def reject(self, log_id: str, path: str, problem: str) -> None:
        target = self.root / "rejected" / f"{log_id}.json"
        tmp = target.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(json.dumps({"log_id": log_id, "path": path, "problem": problem}))
        os.replace(tmp, target)

    def rejected(self) -> list[dict]:
        return [json.loads(p.read_text()) for p in sorted((self.root / "rejected").glob("*.json"))]

    def glob(self, table: str) -> str:
        return str(self.root / "logs" / "*" / f"{table}.parquet")

    def query(self, sql: str) -> pa.Table:
        """DuckDB over the store: ``meta``, ``samples``, ``events``, ``holds``, ``evidence``,
        ``context`` and ``fits`` are views of every file's (every machine's) Parquet files."""
        con = duckdb.connect()
        try:
            for t in TABLES:
                if any((self.root / "logs").glob(f"*/{t}.parquet")):
                    con.execute(f"CREATE VIEW {t} AS SELECT * FROM read_parquet("
                                f"'{self.glob(t)}', union_by_name=true)")
            if any((self.root / "fits").glob("*.parquet")):
                con.execute("CREATE VIEW fits AS SELECT * FROM read_parquet("
                            f"'{self.root / 'fits' / '*.parquet'}', union_by_name=true)")
            return con.sql(sql).to_arrow_table()
        finally:
            con.close()

    def machine_logs(self) -> dict[str, list[str]]:
        """machine -> the ids of its logs and summaries, in time order."""
        if not any((self.root / "logs").glob("*/meta.parquet")):
            return {}
        rows = self.query("SELECT machine, log_id FROM meta ORDER BY machine, start_time_s, "
                          "log_id").to_pylist()
        out: dict[str, list[str]] = {}
        for r in rows:
            out.setdefault(r["machine"], []).append(r["log_id"])
        return out

    def counts(self) -> dict[str, float]:
        """machines, logs, log_hours (the logs' length) and summaries (machine-days) stored."""
        kind = "coalesce(kind, 'log')" if "kind" in self.query(
            "SELECT * FROM meta LIMIT 0").column_names else "'log'"
        return self.query(
            f"SELECT count(*) FILTER (WHERE {kind} = 'log') AS logs, count(DISTINCT machine) "
            f"AS machines, coalesce(sum(duration_s) FILTER (WHERE {kind} = 'log'), 0) / 3600 "
            f"AS log_hours, count(*) FILTER (WHERE {kind} = 'summary') AS summaries FROM meta"
        ).to_pylist()[0]

    def read(self, log_id: str, table: str) -> pa.Table:
        return pq.read_table(self.root / "logs" / log_id / f"{table}.parquet")

    def fits_path(self, machine: str) -> Path:
        return self.root / "fits" / f"{machine}.parquet"
