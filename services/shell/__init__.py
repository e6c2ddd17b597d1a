"""The one Zenoh shell every cvxnav process runs in: session, liveliness, status, bounds, checkpoints."""
