"""Batch and scheduled runs: workflow files (``schema``), the stacks they name and
whether each needs a run (``plan``), the run and its loop (``run``) and the SQLite
ledger with its lock (``ledger``).
"""
