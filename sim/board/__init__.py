"""The leaderboard as a library, under its command (`sim.leaderboard`): the cells and what keeps
them off the board (`cells`), what the board says (`analysis`), its page (`page`) and its plots
(`figures`)."""
