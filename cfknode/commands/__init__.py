"""One module per ``cfknode`` subcommand (see ``cfknode.cli``)."""
