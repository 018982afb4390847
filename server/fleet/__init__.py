"""The fleet link: the one listener to the machine streams, commands, E-STOP, reconciliation, the
result store, and the machines' routes."""
