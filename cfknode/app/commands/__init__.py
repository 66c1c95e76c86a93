"""One module per ``cfknode`` subcommand (see ``cfknode.app.cli``)."""
