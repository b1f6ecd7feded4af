"""The figures of docs/figures/, each drawn from an evaluation report or a bench's output."""
