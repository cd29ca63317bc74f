"""Commissioning a machine nobody modelled: what a calibration day with the position sensor still
fitted measures of it, written into its configuration."""
