"""The panes of the main screen, each a Textual widget over the data: the
frame list (and its keys on held frames), the detail, connections and stats
panes, the filter bar, and the virtual list they draw with."""
