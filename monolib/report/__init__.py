"""Stage 5, the report: the cells' results read back (`results`), intervals and paired differences
(`bootstrap`), the comparison tables built on them (`comparisons`), Tables 1-2 (`tables`), figures (`figures`,
`viz`), the result blocks of README.md and docs/ (`readme`) and the report notebook's one call (`write`). Reads the
files of the stages before it; computes no cached stage output."""
