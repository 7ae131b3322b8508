"""The leaderboard as a library, under its command (`sim.leaderboard`): its tracks (`tracks`: the
tasks and scene shifts), the rows of methods run elsewhere (`poses`), the cells and what keeps
them off the board (`cells`), a cell's figures (`cell_summaries`), the cells paired episode by
episode (`pairs`), what the board says (`analysis`), its page (`page`, its paired sections in
`sections`) and its plots (`figures`)."""
