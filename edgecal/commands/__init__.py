"""The sub-commands of ``edgecal``: one module per command, each with its arguments and its run function."""
