"""Planning the pruning (DESIGN.md's `plan`). Today: cut proposals (`vinetwin propose`), pruning
rules on a twin's skeleton (`rules`), a searched collision-free pruning pose for each cut
(`search`), the proposals written into the twin and reviewed (`proposer`), their settings
(`config`)."""
