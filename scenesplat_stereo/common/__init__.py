"""What every stage shares: files (the one atomic writer), ownership (whether a command may replace an output;
folder locks), the command line's one error path and command table (commandline), text and flag parsing, and the
measuring clock and PSNR (measure).

Public names: ``common.files.atomic_write_bytes``, ``common.ownership.check_replaceable``,
``common.commandline.run_command``, ``common.measure.synced_clock``.
"""
