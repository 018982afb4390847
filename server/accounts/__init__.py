"""Accounts: users, log-in, sessions and the audit log, the log-in guard, their routes and `slinger user`."""
