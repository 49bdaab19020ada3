"""Cut proposals (`vinetwin propose`): pruning rules on a twin's skeleton (`rules`), a searched,
collision-free pruning pose for each cut (`search`), and the proposals written into the twin and
reviewed (`proposer`); the settings in `config`."""
