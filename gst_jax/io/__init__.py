"""Files that outlive a process: work directories, checkpoints, and the Ctrl-C handling that
keeps them whole.

    interrupts.py   SIGINT held back while a checkpoint is written, noticed between steps
    checkpoints.py  orbax checkpoints with checksums, restored with a fall-back
    workdir.py      a work directory's layout, and how a run is named and identified
"""

# The API reference's pages: the files (interrupts.py is how they are kept whole).
__all__ = ["workdir", "checkpoints"]
