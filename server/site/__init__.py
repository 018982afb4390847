"""The site: storage faults, certificates, the Zenoh router, `slinger up` and its supervision, the
health route, and `slinger results`."""
