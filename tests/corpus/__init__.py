"""The fault corpus: `cases` builds the small faulty inputs and checks each case's outcome,
`tally` counts the outcomes and prints them at the end of the test session."""
