"""The floor every package stands on: errors, progress, interrupts, the process set-up (`configure`,
back-end choice, memory), run folders and the named tolerances. Imports nothing else of vdo."""
