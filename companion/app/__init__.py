"""The flight app: vehicle link, state machine, safety, flight log."""
