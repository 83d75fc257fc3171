"""Conformance reports: one data model (``content.build``), several renderings.

Every format renders the same dict, which is also the JSON report, so what a
CI system parses and what a person reads cannot disagree.  This package's
``__init__`` imports nothing, so the command line can name the formats
(``formats``) without loading the analyzer.
"""
