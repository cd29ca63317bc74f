"""Fleet diagnosis: CAN logs of many machines in a columnar store, analysed on Dask.

Needs the ``fleet`` extra (dask[distributed], pyarrow, duckdb); the daemon never imports it.
"""
