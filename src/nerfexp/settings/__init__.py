"""The settings: every key of the composed config has a domain (``schema``), checked on the resolved
values before anything is built (``checks``), and a user's override that does nothing with the rest of
the config is named (``unused``). A bad value is one line naming the key the user sets and what was
expected, before the run's directory is made.
"""
