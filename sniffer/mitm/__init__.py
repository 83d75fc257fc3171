"""The proxy as the man in the middle: faults, interception, injection and scripts."""
