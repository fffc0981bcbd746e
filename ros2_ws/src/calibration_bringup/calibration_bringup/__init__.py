"""Launch script support, parameter files, MCAP recorder, bag player, experiment runner and reports."""
