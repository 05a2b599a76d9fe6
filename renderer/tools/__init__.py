"""What the CLI and the demo build on the renderer: `lodcast render`, `lodcast demo`'s pictures, `lodcast report` (error against time)."""
