"""A config read key by key (nerfexp.config_keys): leaves resolved or as written, and the key a value
comes from, on small configs whose answers are worked out by hand."""

from omegaconf import MISSING, OmegaConf

from nerfexp.config_keys import entries, leaves, source_key

CFG = {
    "hydra": {"job": {"name": "x"}},
    "scale": {"lr": 0.5, "steps": "???", "val_every": 10},
    "trainer": {"max_steps": "${scale.steps}", "val_check_interval": "${scale.val_every}",
                "default_root_dir": "${hydra:runtime.output_dir}"},
    "callbacks": {"every": "${trainer.val_check_interval}"},
    "encoding": {"position": {"n_freqs": 10}},
    "model": {"lr": "${scale.lr}", "skips": [1, "${scale.val_every}"], "encoding": "${encoding.position}"},
}


def test_leaves_are_resolved_a_section_named_by_an_interpolation_walked_where_it_is_named():
    found = dict(leaves(OmegaConf.create(CFG)))
    assert found == {
        "scale.lr": 0.5, "scale.steps": MISSING, "scale.val_every": 10,
        # trainer.max_steps reads the missing scale.steps: left out, scale.steps is the key to name
        "trainer.val_check_interval": 10,
        "trainer.default_root_dir": "${hydra:runtime.output_dir}",  # exists once a job runs: its text
        "callbacks.every": 10,
        "encoding.position.n_freqs": 10,
        "model.lr": 0.5, "model.skips": [1, 10], "model.encoding.n_freqs": 10,
    }
    assert found["scale.steps"] is MISSING and isinstance(found["model.skips"], list)


def test_leaves_leave_out_what_skip_names_with_what_lies_under_it():
    def skip(key, node):
        return key in ("model.encoding", "trainer")

    assert [key for key, _ in leaves(OmegaConf.create(CFG), skip=skip)] == [
        "scale.lr", "scale.steps", "scale.val_every", "callbacks.every", "encoding.position.n_freqs", "model.lr",
        "model.skips"]


def test_the_source_of_a_key_is_followed_through_interpolations_and_sections():
    cfg = OmegaConf.create(CFG)
    assert source_key(cfg, "model.lr") == "scale.lr"
    assert source_key(cfg, "callbacks.every") == "scale.val_every"  # via trainer.val_check_interval
    assert source_key(cfg, "model.encoding.n_freqs") == "encoding.position.n_freqs"  # the section is named
    assert source_key(cfg, "trainer.default_root_dir") == "trainer.default_root_dir"  # a resolver's: no key
    assert source_key(cfg, "scale.lr") == "scale.lr" and source_key(cfg, "no.such") == "no.such"


def test_entries_are_every_key_of_plain_containers_at_every_depth():
    plain = {"a": {"b": [1, {"c": "${x}"}]}, "d": None}
    assert list(entries(plain)) == [("a", plain["a"]), ("a.b", plain["a"]["b"]), ("a.b.0", 1),
                                    ("a.b.1", {"c": "${x}"}), ("a.b.1.c", "${x}"), ("d", None)]
