"""Hosts in network namespaces for the multi-host tests and bench.partition: links, a bad-link proxy, processes."""
