import tools.reproduce_baseline as rb


def test_that_a_tiny_baseline_sweep_reports_mean_and_spread(monkeypatch):
    monkeypatch.setattr(rb, "N_POSITIONS", 2)
    results = [rb.run_case("1", 30), rb.run_case("2", 30)]
    for r in results:
        assert len(r["ra"]) == 2 and all(50 < ra < 100 for ra in r["ra"])
        assert set(r["ve"]) == {"nearest", "leave"}
    text = rb.render(results, 1.0)
    assert "| 1 | 30 % |" in text and "6.1 ± 0.5" in text and "Table 2" in text
