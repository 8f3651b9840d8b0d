(function () {
  var ROWS = JSON.parse(document.getElementById("rows").textContent);
  var ROWS_M = JSON.parse(document.getElementById("rows-m").textContent);  // radii in metres (parts with positions)
  var COLOURS = @COLOURS@, SYMBOLS = @SYMBOLS@;
  var FIGURES = @FIGURES@;
  var FILTERS = [["scale", "scale"], ["noise", "noise"], ["L", "L"], ["mode", "mode"], ["method", "method"],
                 ["radius", "radius (first two figures)"]];
  var TABLE = ["scale", "noise", "L", "series", "family", "params", "radius", "recall", "recall_lo", "recall_hi",
               "bytes_per_place", "us_per_query", "qps_per_core", "n_queries"];
  var TABLE_M = TABLE.slice(0, 6).concat(["part", "radius_m"], TABLE.slice(7));  // radius in metres for radius
  var LEGEND_MAX = 12;  // entries a legend holds and stays readable

  function values(key) {
    var seen = [];
    ROWS.forEach(function (r) { if (r[key] !== null && seen.indexOf(r[key]) < 0) { seen.push(r[key]); } });
    return key === "L" || key === "radius" ? seen.sort(function (a, b) { return a - b; }) : seen;
  }
  // The page opens on one readable view (the first noise level, L = 50 where it was evaluated,
  // recall within 20 frames); the filters live in the address (#noise=qm2&L=all), so a view can
  // be bookmarked or sent, and "all" brings every row back.
  function opening(key, opts) {
    if (key === "noise") { return opts.length > 1 ? String(opts[1]) : "all"; }
    if (key === "L") { return opts.indexOf(50) >= 0 ? "50" : String(opts[opts.length - 1]); }
    if (key === "radius") { return opts.indexOf(20) >= 0 ? "20" : String(opts[opts.length - 1]); }
    return "all";
  }
  ReportPage.filterBar(FILTERS, function (key) { return key === "radius" ? values("radius") : ["all"].concat(values(key)); },
                       opening, function () { draw(); });
  var chosen = ReportPage.chosen, esc = ReportPage.esc;
  function kept(r, withRadius) {
    for (var i = 0; i < FILTERS.length - 1; i++) {
      var k = FILTERS[i][0], v = chosen(k);
      if (v !== "all" && String(r[k]) !== v) { return false; }
    }
    return !withRadius || String(r.radius) === chosen("radius");
  }
  function pct(v) { return v === null ? "–" : (100 * v).toFixed(1); }
  function hover(r) {
    return esc(r.series) + (r.params ? " " + esc(r.params) : "") + "<br>" + esc(r.scale) + ", " +
      esc(String(r.noise).toUpperCase()) + ", L = " + r.L +
      (r.radius_m === undefined ? ", radius " + r.radius : ", " + esc(r.part) + ", within " + r.radius_m + " m") +
      "<br>recall " + pct(r.recall) + " % (" + pct(r.recall_lo) + "–" +
      pct(r.recall_hi) + ")<br>" + (r.us_per_query === null ? "–" : r.us_per_query.toFixed(2)) + " µs/query, " +
      (r.bytes_per_place === null ? "–" : r.bytes_per_place.toFixed(2)) + " B/place, " + r.n_queries + " queries";
  }
  var drawn = {};
  ReportPage.places(FIGURES, drawn, "recall_rows.csv", ROWS);

  function traces(rows, x, lines) {
    var groups = {};
    rows.forEach(function (r) {
      var key = r.series + (lines ? " " + (r.params || "") + " L=" + r.L + " " + r.scale + " " + r.noise +
                            (r.part ? " " + r.part : "") : "");
      (groups[key] = groups[key] || []).push(r);
    });
    return Object.keys(groups).map(function (key) {
      var g = groups[key].slice().sort(function (a, b) { return a[x] - b[x]; }), r0 = g[0];
      return {x: g.map(function (r) { return r[x]; }), y: g.map(function (r) { return 100 * r.recall; }),
              error_y: {type: "data", symmetric: false, visible: !lines, thickness: 1,
                        array: g.map(function (r) { return r.recall_hi === null ? 0 : 100 * (r.recall_hi - r.recall); }),
                        arrayminus: g.map(function (r) { return r.recall_lo === null ? 0 : 100 * (r.recall - r.recall_lo); })},
              mode: lines ? "lines+markers" : "markers", name: esc(key), text: g.map(hover), hoverinfo: "text",
              marker: {color: COLOURS[r0.method] || "#444", symbol: SYMBOLS[r0.mode] || "circle", size: lines ? 5 : 9},
              line: {color: COLOURS[r0.method] || "#444", dash: r0.mode === "paper" ? "dash" : r0.mode === "single" ? "dot" : "solid"}};
    });
  }
  function draw() {
    FIGURES.forEach(function (f) {
      var metres = f[2] === "radius_m", radiusFigure = f[2] === "radius" || metres;
      var rows = (metres ? ROWS_M : ROWS).filter(function (r) { return kept(r, !radiusFigure) && r[f[2]] !== null; });
      drawn[f[0]] = rows;
      var layout = {margin: {t: 20}, hovermode: "closest", legend: {orientation: "v", x: 1.02, y: 1},
                    xaxis: {title: {text: f[3]}, type: radiusFigure ? "linear" : "log", dtick: f[2] === "radius" ? 1 : undefined},
                    yaxis: {title: {text: "recall" + (radiusFigure ? "" : " within " + chosen("radius") + " frames") + " (%)"},
                            range: [0, 102]}};
      var drawnTraces = traces(rows, f[2], radiusFigure);
      layout.showlegend = true;  // beside the plot, scrolling where it holds more lines than fit
      layout.annotations = drawnTraces.length > LEGEND_MAX ? [{text: drawnTraces.length + " lines: choose a noise level, " +
        "L or method above to see fewer (hover names each line)", xref: "paper", yref: "paper", x: 0, y: 1.06,
        showarrow: false, font: {size: 11, color: "#555"}, xanchor: "left"}] : [];
      Plotly.react(f[0], drawnTraces, layout, {responsive: true, displaylogo: false});
      ReportPage.table(f[0], rows, metres ? TABLE_M : TABLE, ["noise", "series"]);
      document.getElementById(f[0]).dataset.points = String(rows.length);
    });
    document.body.dataset.drawn = "yes";
  }
  draw();
})();
