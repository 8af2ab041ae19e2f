"""upright host side: design, analysis, fixed-point export, link clients, HIL runner and CLI."""
