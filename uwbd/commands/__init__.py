"""What ``uwbd`` runs: one module of commands per layer (the daemon's, the logs', the
offline tools', the configuration's), imported by :mod:`uwbd.cli` only for the command
given, so that each command starts with just what it needs; :mod:`.common` holds what they
share."""
