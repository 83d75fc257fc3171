"""Wireshark's side of whiztap: recordings as pcapng files of TCP packets
(``export``), and a Lua dissector generated from the analyzer's own tables
(``dissector``), so network people can read Progwhiz traffic where they
already work (docs/wireshark.md)."""
