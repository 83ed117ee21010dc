"""The compatibility check: the project on the other supported CPythons present (``check.py``)."""
