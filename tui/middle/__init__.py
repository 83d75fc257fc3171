"""The proxy in the middle, as the TUI drives it: the intercept bar, the faults
pane, and the dialogs that edit a held frame or inject one.  Each acts through
the Controller (``data/controls.py``), as ``whiztap ctl`` does, so the recording
says the same whichever was used."""
