"""The subcommands of ``backpack-slam``: one module per command (see ``backpack_slam.cli``)."""
