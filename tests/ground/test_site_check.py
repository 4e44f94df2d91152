"""Where the building stands, checked (`ground.site_check`); the log's building against a `--config` file's [site] is
specified in tests/test_config_options.py."""

from ground.site_check import header_site

SITE = {"lat_deg": 53.4668, "lon_deg": -2.2339, "alt_m": 50.0, "heading_deg": 30.0}


def test_that_a_header_without_a_site_has_none_and_no_warning():
    assert header_site({}) == (None, None)


def test_that_a_header_site_is_read_back_as_its_record():
    record, why = header_site({"site": SITE})
    assert why is None and record == SITE


def test_that_a_malformed_site_is_not_shown_and_says_which_key():
    for bad, key in (({**SITE, "lat_deg": "north"}, "lat_deg"), ({k: v for k, v in SITE.items() if k != "alt_m"},
                                                                   "alt_m"), ([53.0, -2.0], "JSON object")):
        record, why = header_site({"site": bad})
        assert record is None and "malformed" in why and key in why and "not shown" in why
