"""The report formats, named where the command line needs them without
importing the renderers (so `whiztap --help` stays fast)."""

FORMATS = ("text", "json", "junit", "markdown", "html", "sarif", "github")
