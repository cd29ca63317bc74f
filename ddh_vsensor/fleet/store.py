"""The fleet store: one directory of Parquet files, queried with DuckDB.

    DIR/logs/<log_id>/{meta,samples,events,holds}.parquet   one ingested log
    DIR/rejected/<log_id>.json                               a log that could not be read
    DIR/fits/<machine>.parquet                               the per-machine analysis

``log_id`` is a hash of the log's bytes, so ingesting a log twice (under any name) finds it
present. A log's files are written into a temporary directory and renamed into ``logs/`` in
one step: after a crash a log is either complete or absent (the temporary directory is
removed on the next run), so ingestion resumes where it stopped.
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

from ..errors import UserError

TABLES = ("meta", "samples", "events", "holds")


def log_id_of(data: bytes) -> str:
    return hashlib.sha1(data).hexdigest()[:20]


class Store:
    def __init__(self, root: str | Path, create: bool = False) -> None:
        self.root = Path(root)
        if create:
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
        """All tables of one log, atomically (a temporary directory renamed into logs/)."""
        final = self.root / "logs" / log_id
        if final.is_dir():
            return
        tmp = self.root / "tmp" / f"{log_id}.{os.getpid()}"
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        for name, table in tables.items():
            pq.write_table(table, tmp / f"{name}.parquet", compression="zstd")
        with open(tmp / "meta.parquet", "rb") as f:
            os.fsync(f.fileno())
        try:
            os.rename(tmp, final)
        except OSError:                      # another worker put the same log first
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
        """DuckDB over the store: ``meta``, ``samples``, ``events``, ``holds`` and ``fits``
        are views of every log's (every machine's) Parquet files."""
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
        """machine -> its log ids in time order."""
        if not any((self.root / "logs").glob("*/meta.parquet")):
            return {}
        rows = self.query("SELECT machine, log_id FROM meta ORDER BY machine, start_time_s, "
                          "log_id").to_pylist()
        out: dict[str, list[str]] = {}
        for r in rows:
            out.setdefault(r["machine"], []).append(r["log_id"])
        return out

    def read(self, log_id: str, table: str) -> pa.Table:
        return pq.read_table(self.root / "logs" / log_id / f"{table}.parquet")

    def fits_path(self, machine: str) -> Path:
        return self.root / "fits" / f"{machine}.parquet"
