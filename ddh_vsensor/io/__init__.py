"""Measured runs in and out of files: the interchange CSV (:mod:`.csv`), CAN logs in any format
python-can reads (:mod:`.log`), BLF logs a column at a time (:mod:`.blf`), and any of them as a
run (:mod:`.reader`)."""
