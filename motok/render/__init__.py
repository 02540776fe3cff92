"""motok.render"""
