"""experiments.bench.compile_time: how its XLA options are read."""

import pytest

from experiments.bench import compile_time


@pytest.mark.parametrize("text, option", [("xla_backend_optimization_level=1", ("xla_backend_optimization_level", 1)),
                                          ("xla_llvm_disable_expensive_passes=true",
                                           ("xla_llvm_disable_expensive_passes", True)),
                                          ("xla_cpu_max_isa=AVX2", ("xla_cpu_max_isa", "AVX2"))])
def test_xla_options_read_as_the_values_they_spell(text, option):
    assert compile_time.xla_option(text) == option


def test_an_xla_option_without_a_value_is_refused_in_one_line(capsys):
    with pytest.raises(SystemExit):
        compile_time.main(["--xla-option", "xla_backend_optimization_level"])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "NAME=VALUE is allowed" in err
