"""The TUI's data: where traffic comes from (sources), what the screen shows of
it (the model, the frame store and its views, the proxy in the middle's marks
and the server's view, a typed frame judged), and the handles on what runs
beside the app (the proxy's Controller, a replay).  No Textual here: all of it
runs in worker threads or tests without a screen, and the widgets read it."""
