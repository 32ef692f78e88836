"""perfcap serve: the capture service (phone gateway, control API, discovery)."""
