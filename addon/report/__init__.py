"""The HTML report of step folders (``procam report``): its pictures (:mod:`.figures`) and its page (:mod:`.page`).

Reading the folders is the report step's work (``steps/report.py``); this
package turns what it read into one self-contained HTML file.
"""
